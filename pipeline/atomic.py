"""All-or-nothing outputs: a result appears at its path complete, or not at all.

Stages write into a hidden sibling (``.NAME.partial-XXXX``) and rename it into place when they
finish. A failure or an interrupt removes the partial output, and an existing good output is only
replaced (with ``overwrite``) once the new one is complete.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.errors import BTFError


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _sibling(path: Path, tag: str) -> Path:
    suffix = "".join(path.suffixes[-1:])
    stem = path.name[: len(path.name) - len(suffix)] if suffix else path.name
    return path.with_name(f".{stem}.{tag}-{uuid.uuid4().hex[:8]}{suffix}")


@contextmanager
def atomic_output(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path to write to; move it to ``path`` when the block succeeds.

    Parameters
    ----------
    path
        The final output (a file or a directory such as a zarr store).
    overwrite
        Replace an existing output; otherwise an existing output is an error.

    Raises
    ------
    BTFError
        If ``path`` exists and ``overwrite`` is false.
    """
    shown = Path(path)
    path = shown.absolute()  # tasks may run on workers in another directory
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise BTFError(f"{shown}: already exists; pass --overwrite to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _sibling(path, "partial")
    try:
        yield tmp
    except BaseException:
        _remove(tmp)
        raise
    if not tmp.exists():
        raise BTFError(f"{shown}: the stage finished without writing its output")
    if path.exists() or path.is_symlink():
        old = _sibling(path, "old")
        path.rename(old)
        tmp.rename(path)
        _remove(old)
    else:
        tmp.rename(path)
