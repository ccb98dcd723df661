"""Helpers shared by the tests (importable as ``helpers``)."""

from __future__ import annotations

from pathlib import Path

from pipeline.cli import main


def generate_store(path: Path, *args: str) -> Path:
    code = main(["generate", str(path), "--quiet", *args])
    assert code == 0
    return path


def no_partial_outputs(path: Path) -> bool:
    """Neither the output nor any hidden partial sibling of it exists."""
    stem = path.name.split(".")[0]
    leftovers = [p for p in path.parent.glob(f".{stem}*") if "partial" in p.name]
    return not path.exists() and not leftovers
