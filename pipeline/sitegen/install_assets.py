"""Put the reference site's real assets in place: `python -m pipeline.sitegen.install_assets`.

Called at the end of `make setup` (after apt installed `sweethome3d-furniture`, listed in the Makefile's
APT_PACKAGES). It
  1. checks /usr/share/sweethome3d/furniture (the furniture libraries) and says what to install if absent;
  2. fetches the `sweethome3d` .deb with `apt-get download` (the package itself is NOT installed: it pulls a
     Java runtime we do not need), unpacks it in a temporary directory with `dpkg-deb -x` and keeps only the
     jar's resources (textures, door/window/frame/desk models, their two catalogs, LICENSE.TXT) plus the
     Debian copyright file, in `$SITELOC_ASSETS/sweethome3d-jar` (~6 MB), with a SOURCE.json recording the
     package version and sha256 sums;
  3. builds the conversion cache (`assets.load_assets`), so the first test run or render is fast, and writes
     ATTRIBUTION.md next to it.
Exit status 0 when the real assets are in place; 1 with a message saying what to do otherwise (apt missing,
package missing, download failed). SITELOC_SKIP_ASSETS=1 skips everything (exit 0): the site then uses
procedural stand-ins and warns.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.io.atomic import atomic_dir, write_text_atomic
from pipeline.sitegen import assets
from pipeline.sitegen.asset_cache import sha256_file
from pipeline.sitegen.asset_types import CC0, CC_BY, CC_BY_US, AssetLibrary

JAR_IN_DEB = "usr/share/sweethome3d/sweethome3d.jar"
COPYRIGHT_IN_DEB = "usr/share/doc/sweethome3d/copyright"
KEEP_PREFIXES = (assets.JAR_RESOURCES, assets.JAR_FURNITURE_CATALOG, assets.JAR_TEXTURE_CATALOG, "LICENSE.TXT")
SOURCE_FORMAT = 1


@dataclass
class EnsureReport:
    ok: bool = True
    done: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    def fail(self, message: str) -> None:
        self.ok = False
        self.problems.append(message)


LICENSE_URLS = {CC0: "https://creativecommons.org/publicdomain/zero/1.0/",
                CC_BY: "https://creativecommons.org/licenses/by/3.0/",
                CC_BY_US: "https://creativecommons.org/licenses/by/3.0/us/"}

# From the Debian copyright files of sweethome3d-furniture 1.8-1 and sweethome3d 7.0.2+dfsg-3.
SOURCES = (
    ("BlendSwap-CC-0.sh3f", "sweethome3d-furniture (installed)", CC0,
     "2014 Emmanuel Puybaret / eTeks and other contributors; models by Blend Swap users (creator per model)"),
    ("BlendSwap-CC-BY.sh3f", "sweethome3d-furniture (installed)", CC_BY,
     "The Blend Swap contributors (creator per model); cleaned and converted by Emmanuel Puybaret"),
    ("KatorLegaz.sh3f", "sweethome3d-furniture (installed)", CC_BY_US, "2003-2008 Andrew Kator & Jennifer Legaz"),
    ("Scopia.sh3f", "sweethome3d-furniture (installed)", CC_BY,
     "2010-2012 Scopia Visual Interfaces Systems, s.l. (http://www.scopia.es)"),
    ("sweethome3d.jar: io/resources (textures, door/window/frame/desk/plant models)",
     "sweethome3d (.deb downloaded, only these files extracted; not installed)", f"{CC_BY} (or GPL-2+)",
     "2006-2022 Emmanuel Puybaret / eTeks; the catalogs and model files say \"GNU GPL / CC-BY 3.0\", "
     "we use them under CC-BY 3.0"),
)


def attribution_markdown(library: AssetLibrary) -> str:
    """ATTRIBUTION.md: the sources and their licences, then one row per model and texture in `library`."""
    lines = [
        "# Attribution of the reference-site assets",
        "",
        "The embedded reference site (`pipeline/sitegen`) renders furniture models and photographic textures from",
        "Debian's Sweet Home 3D packages. They are not committed: `make setup` installs `sweethome3d-furniture`",
        "and runs `python -m pipeline.sitegen.install_assets`, which also regenerates this list"
        " (`--attribution ATTRIBUTION.md`).",
        "",
        "Changes made (CC-BY asks to say so): models are rotated, rescaled to their catalog size, triangulated and",
        "given generated normals; textures are downscaled; the ceiling textures are eTeks' *Roughcast* lightened",
        "(one with a suspended-ceiling grid drawn on it); posters put photographs (centre-cropped) in eTeks' picture",
        "frame. Nothing here is endorsed by the authors. When an asset is missing, procedural stand-ins made by",
        "siteloc (CC0) are used instead.",
        "",
        "## Sources",
        "",
        "| file | Debian package | licence | copyright |",
        "|---|---|---|---|",
        *(f"| {f} | {pkg} | {lic} | {who} |" for f, pkg, lic, who in SOURCES),
        "",
        "Licences: " + ", ".join(f"[{k}]({v})" for k, v in LICENSE_URLS.items()) + ".",
        "",
        "## Assets used" + (" (procedural stand-ins included)" if library.procedural else ""),
        "",
        "| type | used as | name | creator | licence | source |",
        "|---|---|---|---|---|---|",
    ]
    for row in library.attribution:
        cells = [row["type"], row["used_as"], row["name"], row["creator"], row["license"], row["source"]]
        lines.append("| " + " | ".join(c.replace("|", "/") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def _jar_members(names: list[str]) -> list[str]:
    return [n for n in names if n.startswith(KEEP_PREFIXES) and not n.endswith((".class", "/"))]


def extract_jar(jar: Path, dest: Path, provenance: dict) -> int:
    """Copy the useful members of `jar` into a fresh `dest` (atomically) with SOURCE.json; returns the count."""
    with zipfile.ZipFile(jar) as zf, atomic_dir(dest, force=True, inputs=(jar,)) as tmp:
        members = _jar_members(zf.namelist())
        for name in members:
            target = tmp / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(zf.read(name))
        copyright_file = provenance.pop("copyright_file", None)
        if copyright_file:
            shutil.copyfile(copyright_file, tmp / "debian-copyright")
        source = {"format": SOURCE_FORMAT, "jar_sha256": sha256_file(jar), "members": len(members),
                  "license": "eTeks' models and textures: GPL-2+ or CC-BY-3.0 (used under CC-BY-3.0)", **provenance}
        (tmp / "SOURCE.json").write_text(json.dumps(source, indent=1, sort_keys=True) + "\n")
    return len(members)


def _run(cmd: list[str], cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=False)


def download_jar(dest: Path, log: Callable[[str], None]) -> str | None:
    """`apt-get download sweethome3d` + `dpkg-deb -x` in a temporary directory; returns an error or None."""
    if not shutil.which("apt-get") or not shutil.which("dpkg-deb"):
        return ("apt-get/dpkg-deb not available: this set-up step needs Debian's apt to fetch the `sweethome3d` "
                "package (or set SITELOC_SH3D_JAR to a sweethome3d.jar, or SITELOC_SKIP_ASSETS=1 for procedural "
                "assets)")
    with tempfile.TemporaryDirectory(prefix="siteloc-sh3d-") as tmp_name:
        tmp = Path(tmp_name)
        result = _run(["apt-get", "download", "sweethome3d"], cwd=tmp)
        if result.returncode != 0 and os.geteuid() == 0:
            log("apt-get download failed; refreshing the package lists (apt-get update) and retrying")
            _run(["apt-get", "update", "-qq"])
            result = _run(["apt-get", "download", "sweethome3d"], cwd=tmp)
        debs = sorted(tmp.glob("sweethome3d_*.deb"))
        if result.returncode != 0 or not debs:
            return (f"`apt-get download sweethome3d` failed: {result.stderr.strip()[-400:] or result.stdout[-400:]} "
                    "(try `sudo apt-get update` first)")
        deb = debs[-1]
        unpacked = tmp / "x"
        result = _run(["dpkg-deb", "-x", str(deb), str(unpacked)])
        jar = unpacked / JAR_IN_DEB
        if result.returncode != 0 or not jar.is_file():
            return f"`dpkg-deb -x {deb.name}` gave no {JAR_IN_DEB}: {result.stderr.strip()[-400:]}"
        version = _run(["dpkg-deb", "-f", str(deb), "Version"]).stdout.strip()
        copyright_file = unpacked / COPYRIGHT_IN_DEB
        count = extract_jar(jar, dest, {
            "package": "sweethome3d", "version": version, "deb": deb.name, "deb_sha256": sha256_file(deb),
            "copyright_file": copyright_file if copyright_file.is_file() else None,
        })
        log(f"extracted {count} files of {deb.name} (version {version}) into {dest}")
    return None


def ensure_assets(cache_dir: Path | None = None, *, build_cache: bool = True,
                  log: Callable[[str], None] = print) -> EnsureReport:
    """Make the real assets available (see the module docstring); never raises for a missing tool."""
    report = EnsureReport()
    root = assets.asset_root()
    furniture_dir = assets.default_furniture_dir()
    if sorted(furniture_dir.glob("*.sh3f")):
        report.done.append(f"furniture libraries present in {furniture_dir}")
    else:
        report.fail(f"{furniture_dir} has no *.sh3f: install the furniture libraries with "
                    "`sudo apt-get install sweethome3d-furniture` (make setup does it; no Java needed)")

    jar_source = assets.default_jar_source()
    extracted = root / assets.JAR_DIRNAME
    if jar_source == extracted and (extracted / "SOURCE.json").is_file():
        report.done.append(f"Sweet Home 3D jar resources already extracted in {extracted}")
    elif jar_source.is_file():  # an installed sweethome3d, or SITELOC_SH3D_JAR: copy what we need from it
        count = extract_jar(jar_source, extracted, {"package": "sweethome3d", "jar": str(jar_source)})
        report.done.append(f"extracted {count} files from {jar_source} into {extracted}")
    elif jar_source != extracted and jar_source.is_dir():
        report.done.append(f"using the jar resources in {jar_source} (SITELOC_SH3D_JAR)")
    else:
        error = download_jar(extracted, log)
        if error:
            report.fail(error)
        else:
            report.done.append(f"Sweet Home 3D jar resources extracted into {extracted}")

    if build_cache:
        cache = Path(cache_dir) if cache_dir else root
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", assets.AssetFallbackWarning)
            library = assets.load_assets(cache_dir=cache)
        for w in caught:
            log(f"warning: {w.message}")
        stats = library.stats
        report.done.append(f"conversion cache in {cache}: {int(stats.get('converted', 0))} converted, "
                           f"{int(stats.get('from_cache', 0))} already cached, {stats.get('seconds', 0):.1f} s")
        write_text_atomic(cache / "ATTRIBUTION.md", attribution_markdown(library))
        report.done.append(f"wrote {cache / 'ATTRIBUTION.md'}")
        log(assets.describe(library))
        if library.procedural:
            report.fail("some assets are procedural stand-ins: " + "; ".join(library.missing))
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.sitegen.install_assets",
                                     description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--cache-dir", type=Path, default=None, help="conversion cache (default $SITELOC_ASSETS)")
    parser.add_argument("--no-build", action="store_true", help="only fetch the sources, do not build the cache")
    parser.add_argument("--attribution", type=Path, default=None, help="also write ATTRIBUTION.md here")
    args = parser.parse_args(argv)
    if os.environ.get("SITELOC_SKIP_ASSETS"):
        print("install_assets: SITELOC_SKIP_ASSETS is set; skipped (the site will use procedural assets)")
        return 0
    report = ensure_assets(args.cache_dir, build_cache=not args.no_build)
    if args.attribution and not args.no_build:
        cache = args.cache_dir or assets.asset_root()
        shutil.copyfile(cache / "ATTRIBUTION.md", args.attribution)
        report.done.append(f"wrote {args.attribution}")
    for line in report.done:
        print(f"install_assets: {line}")
    for line in report.problems:
        print(f"install_assets: ERROR: {line}", file=sys.stderr)
    return 0 if report.ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
