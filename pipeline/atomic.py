"""All-or-nothing outputs: a result appears at its path complete, or not at all.

Stages write into a hidden sibling (``.NAME.partial-XXXX``) and rename it into place when they
finish. A failure or an interrupt removes the partial output (stages wait for their running
tasks first, see :meth:`pipeline.session.Session.compute`), except that a full disk keeps a
resumable one (below) so that the same command continues once space is freed. An existing
output is replaced only with ``overwrite``, only once the new one is complete, and only if it is
the same kind of thing (file or folder) and, for a folder, something btf wrote: a store with btf
metadata or a folder of exported layers. A good output is never lost: if the final swap fails,
it is put back.

With ``resume`` (the stage's provenance record) the partial output is named after that record,
``.NAME.resume-KEY``, so a rerun of the same command after the stage was killed (``kill -9``,
the out-of-memory killer) continues in it (:mod:`pipeline.resume`); partial outputs of the
same NAME made with other parameters are removed then. A run holds an exclusive lock
(``.NAME.lock``, :func:`fcntl.flock`) while it writes, so a second run of the same output
fails at once instead of writing into the first one's partial output.

**Object storage** (``s3://`` outputs; :mod:`pipeline.storage`) has no rename, so the same
guarantees take another protocol, written down in docs/cluster-and-storage.md:

- a new output is written in place, under its final prefix, with its root ``zarr.json`` kept
  aside (:data:`pipeline.storage.ASIDE`) and a record of the run's provenance key beside it
  (``.NAME.record``); nothing opens the prefix as a zarr group until the commit, which writes
  the root ``zarr.json`` last (after the consolidated metadata): one ``PUT``. A rerun of the
  same command finds the record and resumes (markers are objects, ``.btf-done/``); a rerun
  with other parameters removes the partial prefix first; a prefix holding objects without a
  record or a root is refused (btf did not write it);
- an existing output is replaced (``overwrite``) through a hidden sibling prefix
  ``.NAME.resume-KEY`` written the same way; once it is complete it is marked
  (``.btf-complete``) and swapped in: the old root ``zarr.json`` is deleted (the old output
  stops opening), then its other objects, then the new objects are copied in on the server,
  the root last, and the sibling is deleted. A run killed during the swap leaves the
  complete sibling: the next run of the same output finishes the swap first. The old output
  is lost only once the new one is complete, and never silently;
- the lock is an object with a lease (:mod:`pipeline.locks`).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline import storage
from pipeline.checksums import MissingChunkError
from pipeline.errors import BTFError
from pipeline.locks import lock as output_lock
from pipeline.resume import DONE, Progress
from pipeline.stores.groups import made_by_btf

COMPLETE = ".btf-complete"  # a complete replacement waiting to be swapped in

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


def _key(record: dict) -> str:
    return hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()
                          ).hexdigest()[:16]


def _resumable(path: Path, record: dict) -> Path:
    """The partial output of ``path`` for the provenance ``record``; stale ones removed.

    A partial output whose skeleton was never completed (killed while it was being created)
    is started over.
    """
    tmp = _sibling(path, "resume", _key(record))
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
        return made_by_btf(attrs)
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


def consolidate(store: str | Path) -> None:
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
        zarr.consolidate_metadata(storage.store(str(store)))


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
    location = storage.parse(path, what="output")
    if storage.is_url(location):
        if not directory:
            raise BTFError(f"{path}: only zarr stores are written to object storage; give a "
                           "local path for an image or report file")
        with _object_output(location, str(path), overwrite=overwrite, resume=resume) as tmp:
            yield tmp
        return
    shown = Path(path)
    path = shown.absolute()  # tasks may run on workers in another directory
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise BTFError(f"{shown}: already exists; pass --overwrite to replace it")
        _check_replaceable(path, shown, directory)
    path.parent.mkdir(parents=True, exist_ok=True)
    if resume is None:
        yield from _fill(_sibling(path, "partial"), path, shown, directory)
        return
    with output_lock(str(path), str(shown)):
        yield from _fill(_resumable(path, resume), path, shown, directory, resumable=True)


def _disk_full(exc: BaseException, folder: Path) -> str | None:
    """What a full disk in ``exc`` (or an error it came from) says, if it is one; else None.

    E.g. ``no space left on the disk of /data (0.4 MiB free)``.
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        code = exc.errno if isinstance(exc, OSError) else None
        if code is None:  # libraries that say it in words (OpenEXR's RuntimeError)
            code = next((c for c in (errno.ENOSPC, errno.EDQUOT) if os.strerror(c) in str(exc)),
                        None)
        if code in (errno.ENOSPC, errno.EDQUOT):
            what = "no space left" if code == errno.ENOSPC else "the disk quota is exceeded"
            try:
                free = f" ({shutil.disk_usage(folder).free / 2**20:.1f} MiB free)"
            except OSError:
                free = ""
            return f"{what} on the disk of {folder}{free}"
        exc = exc.__cause__ or exc.__context__
    return None


def _size(path: Path) -> str:
    """Bytes under ``path``, for a message."""
    total = sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return f"{total / 2**20:.1f} MiB"


def write_whole(out: str, data: bytes, overwrite: bool) -> None:
    """The file ``out`` written whole: a page, a picture, a record.

    Locally through :func:`atomic_output` (a sibling and a rename); in object storage as one
    ``PUT`` (an object appears complete or not at all).
    """
    location = storage.parse(out, what="output")
    if not storage.is_url(location):
        with atomic_output(out, directory=False, overwrite=overwrite) as tmp:
            Path(tmp).write_bytes(data)
        return
    if storage.exists(location) and not overwrite:
        raise BTFError(f"{out}: already exists; pass --overwrite to replace it")
    storage.write(location, data)


def _fill(tmp: Path, path: Path, shown: Path, directory: bool, *,
          resumable: bool = False) -> Iterator[Path]:
    """The body of :func:`atomic_output` once ``tmp`` is chosen: yield it, then swap.

    A full disk (or quota) is one message; a ``resumable`` partial output is then kept, so that
    the same command continues once space is freed.
    """
    try:
        yield tmp
    except BaseException as exc:
        full = _disk_full(exc, path.parent)
        if full and resumable:
            raise BTFError(f"{shown}: {full} while writing it; the work done so far is kept "
                           f"in {tmp} ({_size(tmp)}): free space and run the same command "
                           "again to continue where it stopped") from None
        try:
            _remove(tmp)
        except OSError as err:
            exc.add_note(f"the partial output {tmp} could not be removed: {err}")
        if full:
            raise BTFError(f"{shown}: {full} while writing it; nothing was written (an output "
                           "already there is untouched): free space and run it again") from None
        raise
    if not tmp.exists():
        raise BTFError(f"{shown}: the stage finished without writing its output")
    if directory:
        _remove(tmp / DONE)
    if directory and (tmp / "zarr.json").is_file():
        from pipeline import completeness

        try:
            completeness.seal(str(tmp), str(shown))
        except MissingChunkError:
            _remove(tmp)
            raise
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


@contextmanager
def atomic_subtree(root: str, name: str) -> Iterator[str]:
    """Yield the path, inside store ``root``, of a hidden group to write in place of ``name``.

    When the block succeeds the new group replaces ``name`` (the levels of ``btf pyramid``);
    when it fails, it is removed and ``name`` is left as it was. Partial groups a killed run
    left are removed first. Locally the swap is two renames, so the old group stays whole
    until the new one is in place. In object storage there is no rename: the old group is
    deleted, then the new one copied in on the server (a run killed in between leaves a store
    without ``name``, which the stage that wrote it makes again).
    """
    for stale in storage.children(root):  # left by a killed run
        if stale.startswith(f".{name}."):
            storage.remove(storage.join(root, stale))
    partial = f".{name}.partial-{uuid.uuid4().hex[:8]}"
    try:
        yield partial
    except BaseException:
        storage.remove(storage.join(root, partial))
        raise
    target, new = storage.join(root, name), storage.join(root, partial)
    from pipeline.completeness import missing_error

    if (error := missing_error(new, f"{storage.shown(root)}: group {name!r}")) is not None:
        storage.remove(new)
        raise error
    if storage.is_url(root):
        storage.remove(target)
        storage.copy_tree(new, target)
        storage.remove(new)
        if (error := missing_error(target, f"{storage.shown(root)}: group {name!r}")):
            storage.remove(target)  # as a run killed during the swap leaves it (above)
            raise error
        return
    old = storage.join(root, f".{name}.old-{uuid.uuid4().hex[:8]}")
    if Path(target).exists():
        Path(target).rename(old)
    Path(new).rename(target)
    storage.remove(old)


def _root_attrs(location: str) -> dict | None:
    """The attrs in a store's root metadata, or ``None`` when it has none."""
    raw = storage.read(storage.join(location, storage.ROOT))
    if raw is None:
        return None
    try:
        return json.loads(raw).get("attributes", {})
    except ValueError:
        return {}


def _finish_swaps(url: str, shown: str) -> bool:
    """Complete a replacement a killed run had started swapping in (see the module).

    Returns whether there was one. The caller holds the output's lock.
    """
    prefix = f".{storage.name(url)}.resume-"
    finished = False
    for child in storage.children(storage.parent(url)):
        staged = storage.join(storage.parent(url), child)
        if child.startswith(prefix) and storage.exists(storage.join(staged, COMPLETE)):
            _swap(staged, url)
            finished = True
    return finished


def finish_swaps(url: str, shown: str) -> bool:
    """:func:`_finish_swaps` for a reader that found no store at ``url``, under the lock.

    A run killed while it copied a complete replacement into place leaves ``url`` without its
    root metadata; the replacement is whole beside it, and the first reader puts it in place.
    """
    prefix = f".{storage.name(url)}.resume-"
    if not any(c.startswith(prefix) for c in storage.children(storage.parent(url))):
        return False
    with output_lock(url, shown):
        return _finish_swaps(url, shown)


def _swap(staged: str, url: str) -> None:
    """Replace ``url`` by the complete output at ``staged`` (see the module)."""
    storage.remove(storage.join(url, storage.ROOT))  # the old output stops opening first
    storage.remove(url)
    storage.copy_tree(staged, url, last=(storage.ROOT,), skip=(COMPLETE,))
    storage.remove(staged)  # its mark of completeness last: a kill before this copies again


@contextmanager
def _object_output(url: str, shown: str, *, overwrite: bool, resume: dict | None
                   ) -> Iterator[str]:
    """:func:`atomic_output` on object storage (see the module)."""
    with output_lock(url, shown):
        _finish_swaps(url, shown)
        attrs = _root_attrs(url)
        if attrs is not None:
            if not overwrite:
                raise BTFError(f"{shown}: already exists; pass --overwrite to replace it")
            if not made_by_btf(attrs):
                raise BTFError(f"{shown}: refusing to replace a store that btf did not write")
            staged = storage.join(storage.parent(url), f".{storage.name(url)}.resume-"
                                  + (_key(resume) if resume else uuid.uuid4().hex[:16]))
            for child in storage.children(storage.parent(url)):  # stale replacements
                other = storage.join(storage.parent(url), child)
                if child.startswith(f".{storage.name(url)}.resume-") and other != staged:
                    storage.remove(other)
            if storage.any_below(staged) and not Progress(staged).created:
                storage.remove(staged)  # killed while its skeleton was made or committed
            yield from _fill_object(staged, shown)
            storage.write(storage.join(staged, COMPLETE), b"")
            _swap(staged, url)
            return
        key = _key(resume) if resume else uuid.uuid4().hex[:16]
        record_at = _record(url)
        record = storage.read(record_at)
        if record is None and storage.any_below(url):
            raise BTFError(f"{shown}: holds objects btf did not write (no {storage.ROOT}, no "
                           f"{record_at}); refusing to write over them")
        if record is not None and (resume is None or record.decode() != key
                                   or not Progress(url).created):
            storage.remove(url)  # of other parameters, or killed before it could resume
        storage.write(record_at, key.encode())
        storage.hide_root(url)
        try:
            yield from _fill_object(url, shown, in_place=True)
        finally:
            storage.show_root(url)


def _record(url: str) -> str:
    """Where an in-place partial output's provenance key is kept: beside it."""
    return storage.join(storage.parent(url), f".{storage.name(url)}.record")


def _fill_object(tmp: str, shown: str, *, in_place: bool = False) -> Iterator[str]:
    """Yield ``tmp``; then drop its markers and commit its metadata (root last).

    An error or an interrupt removes the partial output, as locally: resuming is for runs
    that were killed before they could clean up.
    """
    try:
        yield tmp
    except BaseException as exc:
        try:
            storage.remove(tmp)
            # the record goes only with the last object: what is left (a write that landed
            # after the removal listed the prefix) stays btf's, for the next run to remove
            if in_place and not storage.any_below(tmp):
                storage.remove(_record(tmp))
        except BTFError as err:
            exc.add_note(f"the partial output {tmp} could not be removed: {err}")
        raise
    if not storage.any_below(tmp):
        raise BTFError(f"{shown}: the stage finished without writing its output")
    storage.remove(storage.join(tmp, DONE))
    from pipeline import completeness

    try:
        completeness.seal(tmp, shown)
    except MissingChunkError:
        storage.remove(tmp)
        if in_place:
            storage.remove(_record(tmp))
        raise
    if not in_place:
        consolidate(tmp)
        return
    consolidate(tmp)  # writes the root metadata aside (storage.ASIDE)
    root = storage.join(tmp, storage.ASIDE)
    storage.write(storage.join(tmp, storage.ROOT), storage.read(root))  # the commit
    storage.remove(root)
    storage.remove(_record(tmp))
