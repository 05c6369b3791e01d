"""Outputs never overlap inputs: refused before anything is touched, in every stage that publishes a directory."""

from __future__ import annotations

import ast
import os
from pathlib import Path

import pytest

from pipeline.errors import OutputExistsError, OutputOverlapsInputError
from pipeline.io.atomic import atomic_dir, check_output, refuse_overlap

ROOT = Path(__file__).resolve().parents[2]


def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def site(tmp_path) -> Path:
    root = tmp_path / "site"
    (root / "images").mkdir(parents=True)
    (root / "captures.csv").write_text("image\n")
    (root / "images" / "a.jpg").write_bytes(b"\xff\xd8")
    return root


@pytest.mark.parametrize("rel, how", [("site", "is the input"), ("site/images", "is inside the input"),
                                      (".", "contains the input"), ("site/new", "is inside the input")])
def test_overlapping_output_is_refused_and_input_untouched(site, rel, how):
    before = tree(site.parent)
    out = site.parent / rel
    with pytest.raises(OutputOverlapsInputError, match=how):
        with atomic_dir(out, force=True, inputs=[site]) as tmp:
            (tmp / "x").write_text("written")
    assert tree(site.parent) == before
    assert not (site / "new").exists()


def test_siblings_and_name_prefixes_do_not_overlap(site):
    refuse_overlap(site.parent / "site-out", [site])
    refuse_overlap(site.parent / "sit", [site])
    with atomic_dir(site.parent / "site2", inputs=[site, None, [site / "captures.csv"]]) as tmp:
        (tmp / "x").write_text("ok")
    assert (site.parent / "site2" / "x").read_text() == "ok"


def test_links_are_resolved_and_lists_are_flattened(site, tmp_path):
    link = tmp_path / "link"
    os.symlink(site, link)
    with pytest.raises(OutputOverlapsInputError):
        refuse_overlap(link / "images", [site])
    with pytest.raises(OutputOverlapsInputError):
        refuse_overlap(site / "images", [[tmp_path / "other.bag", site / "images" / "a.jpg"]])


def test_check_output_order(site):
    with pytest.raises(OutputOverlapsInputError):  # overlap first: --force does not make it safe
        check_output(site, force=True, inputs=[site])
    with pytest.raises(OutputExistsError):
        check_output(site, force=False, inputs=[])
    check_output(site, force=True, inputs=[])


def test_every_atomic_dir_call_names_its_inputs():
    """A stage that publishes a directory says what it read, so the guard cannot be forgotten."""
    missing = []
    for path in sorted((ROOT / "pipeline").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "atomic_dir"
                    and not any(k.arg == "inputs" for k in node.keywords)):
                missing.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not missing, missing
