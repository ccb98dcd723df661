"""All-or-nothing outputs: a result appears at its path complete, or not at all.

Stages write into a hidden sibling (``.NAME.partial-XXXX``) and rename it into place when they
finish. A failure or an interrupt removes the partial output (stages wait for their running
tasks first, see :meth:`pipeline.session.Session.compute`). An existing output is replaced only
with ``overwrite``, only once the new one is complete, and only if it is the same kind of thing
(file or folder) and, for a folder, something btf wrote: a store with btf metadata or a folder of
exported layers. A good output is never lost: if the final swap fails, it is put back.

With ``resume`` (the stage's provenance record) the partial output is named after that record,
``.NAME.resume-KEY``, so a rerun of the same command after the stage was killed (``kill -9``,
the out-of-memory killer) continues in it (:mod:`pipeline.resume`); partial outputs of the
same NAME made with other parameters are removed then. A run holds an exclusive lock
(``.NAME.lock``, :func:`fcntl.flock`) while it writes, so a second run of the same output
fails at once instead of writing into the first one's partial output.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.errors import BTFError
from pipeline.resume import DONE, Progress

_EXPORTED = {".exr", ".png", ".csv"}


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _sibling(path: Path, tag: str, key: str | None = None) -> Path:
    suffix = "".join(path.suffixes[-1:])
    stem = path.name[: len(path.name) - len(suffix)] if suffix else path.name
    return path.with_name(f".{stem}.{tag}-{key or uuid.uuid4().hex[:8]}{suffix}")


def _resumable(path: Path, record: dict) -> Path:
    """The partial output of ``path`` for the provenance ``record``; stale ones removed.

    A partial output whose skeleton was never completed (killed while it was being created)
    is started over.
    """
    key = hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()
    tmp = _sibling(path, "resume", key[:16])
    for stale in path.parent.glob(_sibling(path, "resume", "*").name):
        if stale != tmp:
            _remove(stale)
    if tmp.exists() and not Progress(tmp).created:
        _remove(tmp)
    return tmp


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
def atomic_output(path: str | os.PathLike, *, directory: bool, overwrite: bool = False,
                  resume: dict | None = None) -> Iterator[Path]:
    """Yield a temporary path to write to; move it to ``path`` when the block succeeds.

    Parameters
    ----------
    path
        The final output.
    directory
        Whether the output is a folder (a store, exported layers) rather than a file.
    overwrite
        Replace an existing output (of the same kind, written by btf).
    resume
        The stage's provenance record: name the partial output after it, so that a rerun of
        a killed stage continues where it stopped (see the module).

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
    lock = None if resume is None else _lock(path, shown)
    try:
        tmp = _sibling(path, "partial") if resume is None else _resumable(path, resume)
        yield from _fill(tmp, path, shown, directory)
    finally:
        if lock is not None:
            _unlock(lock)


def _lock(path: Path, shown: Path):
    import fcntl

    lock = path.with_name(f".{path.name}.lock").open("w")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        lock.close()
        raise BTFError(f"{shown}: another btf run is writing this output (it holds "
                       f"{lock.name}); wait for it to end") from None
    return lock


def _unlock(lock) -> None:
    Path(lock.name).unlink(missing_ok=True)
    lock.close()


def _fill(tmp: Path, path: Path, shown: Path, directory: bool) -> Iterator[Path]:
    """The body of :func:`atomic_output` once ``tmp`` is chosen: yield it, then swap."""
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
    if directory:
        _remove(tmp / DONE)
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
