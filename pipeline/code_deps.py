"""The code a `siteloc` command runs: the project files it imports, found by reading their source.

dvc.yaml lists each stage's code as `deps` so that DVC reruns a stage when its code changes; this module
computes what that list must cover (tests/test_dvc.py checks dvc.yaml against it). Every `import` in a
file counts, including those inside functions (commands import heavy modules lazily), so the set is a
superset of what one run executes; package __init__ files that hold only a docstring
are left out. `python -m pipeline.code_deps` prints it for every stage of dvc.yaml.
"""

from __future__ import annotations

import ast
import inspect
import sys
import textwrap
from collections.abc import Callable, Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("pipeline", "stages")


def _module_file(module: str) -> Path | None:
    """The source file of a project module (`pipeline.io.tables` -> pipeline/io/tables.py), or None."""
    if module.split(".")[0] not in PACKAGES:
        return None
    base = ROOT.joinpath(*module.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imported_modules(tree: ast.AST, package: str) -> Iterable[str]:
    """Dotted names of every module an AST imports; `from a import b` yields `a` and `a.b` (b may be a module)."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the importing package
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            yield base
            yield from (f"{base}.{alias.name}" for alias in node.names)


def _package_of(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    return ".".join(parts[:-1] if parts[-1] != "__init__" else parts[:-1])


def _closure(start: Iterable[Path]) -> set[Path]:
    seen: set[Path] = set()
    todo = list(start)
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        # A module's package __init__ files run before it.
        for parent in path.relative_to(ROOT).parents:
            init = ROOT / parent / "__init__.py"
            if parent != Path(".") and init.is_file() and init not in seen:
                todo.append(init)
        tree = ast.parse(path.read_text(), filename=str(path))
        for name in _imported_modules(tree, _package_of(path)):
            found = _module_file(name)
            if found is not None and found not in seen:
                todo.append(found)
    return seen


def _runs_code(path: Path) -> bool:
    """Whether a file does anything when imported: a package __init__ holding only a docstring does not."""
    body = ast.parse(path.read_text()).body
    return any(not (isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)) for n in body)


def code_of(callback: Callable) -> set[Path]:
    """Project files a command's function may import: its own file's top-level imports and its body's."""
    source_file = Path(inspect.getsourcefile(callback)).resolve()
    module_tree = ast.parse(source_file.read_text())
    top_level = [n for n in module_tree.body if isinstance(n, ast.Import | ast.ImportFrom)]
    body = ast.parse(textwrap.dedent(inspect.getsource(callback)))
    package = _package_of(source_file)
    names = [*_imported_modules(ast.Module(body=top_level, type_ignores=[]), package),
             *_imported_modules(body, package)]
    # The command's own file counts, but only the imports this command makes are followed (one file in
    # stages/ holds several commands).
    found = {source_file} | _closure(f for f in map(_module_file, names) if f is not None and f != source_file)
    return {f for f in found if _runs_code(f)}


def command_callback(words: list[str]) -> Callable:
    """The function behind `siteloc WORDS...` (`["prior", "build"]` -> stages.prior.build)."""
    from typer.main import get_command

    from stages.app import app

    command = get_command(app)
    for word in words:
        if word not in getattr(command, "commands", {}):
            raise KeyError(f"siteloc {' '.join(words)}: no such command")
        command = command.commands[word]
    callback = command.callback
    return getattr(callback, "__wrapped__", callback)  # typer wraps the command's own function


def stage_command_words(cmd: str) -> list[str]:
    """The command words of a dvc.yaml `cmd` (`siteloc prior build X --out Y` -> ["prior", "build"])."""
    words = cmd.split()
    if words[0] != "siteloc":
        raise ValueError(f"not a siteloc command: {cmd}")
    out = []
    for w in words[1:]:
        if w.startswith("-") or "/" in w or "$" in w or "." in w:
            break
        out.append(w)
        if w not in ("prior", "config"):  # the two command groups
            break
    return out


def covered(path: Path, deps: Iterable[str]) -> bool:
    """Whether a file is inside one of dvc.yaml's dependency paths (files or folders, relative to ROOT)."""
    rel = path.relative_to(ROOT)
    return any(rel == Path(d) or Path(d) in rel.parents for d in deps)


def main() -> None:  # pragma: no cover - a helper for whoever edits dvc.yaml
    import yaml

    doc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    for name, stage in doc["stages"].items():
        stage = stage.get("do", stage)
        files = sorted(p.relative_to(ROOT).as_posix() for p in code_of(command_callback(
            stage_command_words(stage["cmd"]))))
        missing = [f for f in files if not covered(ROOT / f, stage.get("deps", []))]
        print(f"{name}: {len(files)} files" + (f"; not in deps: {' '.join(missing)}" if missing else ""))
    sys.exit(0)


if __name__ == "__main__":
    main()


def import_cycles() -> list[list[str]]:
    """Groups of project modules that import each other, directly or through others (every import
    counts, lazy ones included; package __init__ files do not): each such group is a design debt."""
    import numpy as np
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    paths = sorted([*ROOT.joinpath("pipeline").rglob("*.py"), *ROOT.joinpath("stages").rglob("*.py")])
    index = {p: i for i, p in enumerate(paths)}
    edges = set()
    for path in paths:
        for name in _imported_modules(ast.parse(path.read_text()), _package_of(path)):
            found = _module_file(name)
            if found is not None and found != path and found.name != "__init__.py":
                edges.add((index[path], index[found]))
    rows, cols = (np.array(x, dtype=np.int64) for x in zip(*edges, strict=True)) if edges else ([], [])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(paths), len(paths)))
    _, label = connected_components(graph, directed=True, connection="strong")
    groups = [np.nonzero(label == g)[0] for g in np.unique(label)]
    return sorted(sorted(paths[i].relative_to(ROOT).as_posix() for i in g) for g in groups if len(g) > 1)
