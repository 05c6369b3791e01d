"""How export publishes a bundle: the archive before the directory, so a published directory always has
its archive, whatever moment the export is killed at; a directory left without its archive is completed."""

from __future__ import annotations

import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from pipeline.bundle.export import archive_matches, archive_of, complete_archive, publish_bundle, write_manifest
from pipeline.runtime.bundle import BundleError, open_bundle, read_manifest, verify_bundle

REPO = Path(__file__).resolve().parents[2]
SETTINGS = """filter: {}
retrieval: {top_n: 4, rerank: true, query_regions: 10, candidate_weights: [4.0, 3.0, 2.0, 1.0]}
laser: {angle_min: -1.5, angle_increment: 0.01, range_max: 10.0, base_from_laser: [0.0, 0.0, 0.0]}
"""

# Writes a small bundle through `publish_bundle` (what `run_export` publishes with) and, as asked, SIGKILLs
# itself while the archive is being written (after its first file member) or once the archive is published.
EXPORT = f"""
import os, signal, sys, tarfile
from pathlib import Path
import pipeline.bundle.export as ex
out, kill, force, tag = Path(sys.argv[1]), sys.argv[2], sys.argv[3] == "force", sys.argv[4]
if kill == "archive":
    add = tarfile.TarFile.addfile
    def dying(self, tarinfo, fileobj=None, *args, **kw):
        add(self, tarinfo, fileobj, *args, **kw)
        if tarinfo.isfile():
            os.kill(os.getpid(), signal.SIGKILL)
    tarfile.TarFile.addfile = dying
elif kill == "published":
    write = ex.write_archive
    def dying(*args, **kw):
        write(*args, **kw)
        os.kill(os.getpid(), signal.SIGKILL)
    ex.write_archive = dying
with ex.publish_bundle(out, force=force, inputs=()) as tmp:
    (tmp / "db").mkdir()
    (tmp / "db" / "a.bin").write_bytes(os.urandom(300_000))
    (tmp / "filter.yaml").write_text({SETTINGS!r})
    ex.write_manifest(tmp, {{"bundle_version": "1.0", "site": "site", "tag": tag}})
"""


def export(out: Path, kill: str = "none", *, force: bool = False, tag: str = "new") -> int:
    return subprocess.run([sys.executable, "-c", EXPORT, str(out), kill, "force" if force else "-", tag],
                          cwd=REPO, capture_output=True, text=True, timeout=120).returncode


def published_together(out: Path) -> bool:
    """No directory, or a directory whose archive holds exactly its files."""
    return not out.exists() or archive_matches(archive_of(out), out, read_manifest(out))


def clean(out: Path) -> bool:
    return sorted(p.name for p in out.parent.iterdir()) == [out.name, archive_of(out).name]


@pytest.mark.parametrize("kill", ["archive", "published"])
def test_an_export_killed_while_publishing_never_leaves_a_directory_without_its_archive(tmp_path, kill):
    out = tmp_path / "bundles" / "site-1.0"
    assert export(out, kill) == -9
    assert published_together(out) and not out.exists()
    left = sorted(p.name for p in out.parent.iterdir())
    if kill == "archive":  # killed mid-archive: both temporaries are there, nothing is published
        assert any(n.startswith(".site-1.0.tmp-") for n in left) and any(n.endswith(".tmp-write") for n in left)
        assert not archive_of(out).exists()
    else:  # the archive was published, the directory not yet
        assert archive_of(out).is_file()
    assert export(out) == 0
    assert clean(out) and published_together(out)  # no stale temporary of either kind
    assert read_manifest(open_bundle(archive_of(out), tmp_path / "unpacked"))["tag"] == "new"


@pytest.mark.parametrize("kill", ["archive", "published"])
def test_a_forced_export_killed_while_publishing_leaves_a_usable_directory_and_archive(tmp_path, kill):
    out = tmp_path / "bundles" / "site-1.0"
    assert export(out, tag="old") == 0
    assert export(out, kill, force=True) == -9
    assert out.is_dir() and archive_of(out).is_file() and read_manifest(out)["tag"] == "old"
    # killed mid-archive, the old archive is untouched; killed after it, the new archive is beside the old
    # directory: the next export without --force rebuilds it (and either way removes the stale temporaries)
    assert published_together(out) is (kill == "archive")
    assert complete_archive(out) is (kill == "published")
    assert published_together(out) and clean(out)
    assert export(out, force=True) == 0
    assert clean(out) and published_together(out) and read_manifest(out)["tag"] == "new"


@pytest.fixture
def bundle(tmp_path) -> Path:
    out = tmp_path / "bundles" / "site-1.0"
    with publish_bundle(out, inputs=()) as tmp:
        (tmp / "db").mkdir()
        (tmp / "db" / "a.bin").write_bytes(bytes(range(256)) * 64)
        (tmp / "filter.yaml").write_text(SETTINGS)
        write_manifest(tmp, {"bundle_version": "1.0", "site": "site"})
    return out


def test_publishing_writes_both_and_an_aborted_block_writes_neither(tmp_path, bundle):
    assert clean(bundle) and published_together(bundle)
    out = tmp_path / "bundles" / "site-2.0"
    with pytest.raises(RuntimeError), publish_bundle(out, inputs=()) as tmp:
        (tmp / "x").write_text("x")
        raise RuntimeError("export failed")
    assert not out.exists() and not archive_of(out).exists()
    assert sorted(p.name for p in out.parent.iterdir()) == [bundle.name, archive_of(bundle).name]


@pytest.mark.parametrize("damage", ["missing", "truncated", "other export"])
def test_a_directory_without_its_matching_archive_gets_it_rebuilt(tmp_path, bundle, damage):
    archive = archive_of(bundle)
    if damage == "missing":
        archive.unlink()
    elif damage == "truncated":
        archive.write_bytes(archive.read_bytes()[:-100])
    else:
        with tarfile.open(archive, "w:gz") as tar:
            tar.add(bundle / "filter.yaml", arcname="site-1.0/filter.yaml")
    (tmp_path / "bundles" / ".site-1.0.tar.gz.x1.tmp-write").write_bytes(b"stale")
    assert complete_archive(bundle) is True
    assert published_together(bundle) and clean(bundle)
    assert verify_bundle(open_bundle(archive, tmp_path / "unpacked")) == verify_bundle(bundle)
    assert complete_archive(bundle) is False  # complete now: an export without --force says "exists"


def test_a_directory_without_its_archive_that_does_not_verify_is_refused_saying_force(bundle):
    archive_of(bundle).unlink()
    (bundle / "db" / "a.bin").write_bytes(b"altered")
    with pytest.raises(BundleError, match=r"(?s)site-1\.0: exists, but site-1\.0\.tar\.gz is missing or does not "
                                          r"match it and the directory does not verify: .*a\.bin: 7 bytes.*--force"):
        complete_archive(bundle)
    assert not archive_of(bundle).exists()


def test_the_dvc_export_stage_has_the_archive_among_its_outs():
    """DVC decides from the outs whether `export` must run again: a missing archive must count."""
    import yaml

    stage = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]["export"]
    assert "bundles/${synth.site}-${export.version}.tar.gz" in stage["outs"]
    assert "bundles/${synth.site}-${export.version}" in stage["outs"]
    assert "--force" in stage["cmd"]


def test_stale_temporaries_are_only_this_bundles(tmp_path, bundle):
    other = tmp_path / "bundles" / ".site-1.0.1.tmp-abc"  # another bundle's (site-1.0.1) temporary
    other.mkdir()
    mine = tmp_path / "bundles" / ".site-1.0.tmp-abc"
    mine.mkdir()
    from pipeline.bundle.export import clean_stale

    clean_stale(bundle)
    assert other.exists() and not mine.exists() and published_together(bundle)
