"""All-or-nothing outputs: a result appears at its path complete, or not at all.

Stages write into a hidden sibling (``.NAME.partial-XXXX``) and rename it into place when they
finish. A failure or an interrupt removes the partial output (stages wait for their running
tasks first, see :meth:`pipeline.session.Session.compute`). An existing output is replaced only
with ``overwrite``, only once the new one is complete, and only if it is the same kind of thing
(file or folder) and, for a folder, something btf wrote: a store with btf metadata or a folder of
exported layers. A good output is never lost: if the final swap fails, it is put back.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.errors import BTFError

_EXPORTED = {".exr", ".png", ".csv"}


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _sibling(path: Path, tag: str) -> Path:
    suffix = "".join(path.suffixes[-1:])
    stem = path.name[: len(path.name) - len(suffix)] if suffix else path.name
    return path.with_name(f".{stem}.{tag}-{uuid.uuid4().hex[:8]}{suffix}")


def written_by_btf(path: Path) -> bool:
    """Whether a folder is a btf output: a zarr store with btf attrs, or exported layers."""
    meta = path / "zarr.json"
    if meta.is_file():
        try:
            attrs = json.loads(meta.read_text()).get("attributes", {})
        except (OSError, ValueError):
            return False
        return "btf_kind" in attrs or "provenance" in attrs
    entries = list(path.iterdir())
    return (path / "manifest.csv").is_file() and all(
        e.is_file() and e.suffix.lower() in _EXPORTED for e in entries)


def _check_replaceable(path: Path, shown: Path, directory: bool) -> None:
    if path.is_dir() != directory:
        what = "a folder" if path.is_dir() else "a file"
        raise BTFError(f"{shown}: is {what}; refusing to replace it with "
                       f"{'a folder' if directory else 'a file'}")
    if directory and not written_by_btf(path):
        raise BTFError(f"{shown}: refusing to replace a folder that btf did not write "
                       "(no btf store or exported layers in it)")


def consolidate(store: Path) -> None:
    """Write the store's consolidated metadata (zarr v3), so that opening it reads one file.

    Called on every store a stage finishes, after its last write and before it appears at its
    path; ``xarray.open_zarr(path)`` then opens it quietly. zarr-python warns that consolidated
    metadata is not yet part of the v3 specification (it is a zarr-python extension, which
    xarray reads); readers without it fall back to the per-array metadata, which stays. btf
    itself reads the per-array metadata (``use_consolidated=False``), so a store edited by hand
    afterwards is judged by its files, not by a stale copy.
    """
    import warnings

    import zarr

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")
        zarr.consolidate_metadata(str(store))


@contextmanager
def atomic_output(path: str | os.PathLike, *, directory: bool,
                  overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path to write to; move it to ``path`` when the block succeeds.

    Parameters
    ----------
    path
        The final output.
    directory
        Whether the output is a folder (a store, exported layers) rather than a file.
    overwrite
        Replace an existing output (of the same kind, written by btf).

    Raises
    ------
    BTFError
        If ``path`` exists and may not be replaced.
    """
    shown = Path(path)
    path = shown.absolute()  # tasks may run on workers in another directory
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise BTFError(f"{shown}: already exists; pass --overwrite to replace it")
        _check_replaceable(path, shown, directory)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _sibling(path, "partial")
    try:
        yield tmp
    except BaseException as exc:
        try:
            _remove(tmp)
        except OSError as err:
            exc.add_note(f"the partial output {tmp} could not be removed: {err}")
        raise
    if not tmp.exists():
        raise BTFError(f"{shown}: the stage finished without writing its output")
    if directory and (tmp / "zarr.json").is_file():
        consolidate(tmp)
    if not (path.exists() or path.is_symlink()):
        tmp.rename(path)
        return
    old = _sibling(path, "old")
    path.rename(old)
    try:
        tmp.rename(path)
    except BaseException:
        old.rename(path)  # put the good output back
        _remove(tmp)
        raise
    _remove(old)
