"""How an output was made: the stage, its parameters, the equivalent command and the version.

Provenance holds nothing that depends on where or when the stage ran (no scheduler, no clock),
so the same parameters give byte-identical stores on every scheduler, and a run can tell that
an existing output is already what was asked for.
"""

from __future__ import annotations

import dataclasses
import hashlib
import shlex
from pathlib import Path
from typing import Any

from pipeline import __version__, storage
from pipeline.params import key_of, paths, to_record


def command_line(stage: str, params: Any) -> str:
    """The ``btf`` command that gives ``params`` (every recorded parameter spelled out)."""
    words = ["btf", stage]
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if not f.metadata.get("record", True) or value is None or value is False:
            continue
        if isinstance(value, tuple):
            value = ",".join(map(str, value))
        if f.metadata.get("positional"):
            words.append(str(value))
        elif value is True:
            words.append("--" + key_of(f).replace("_", "-"))
        else:
            words += ["--" + key_of(f).replace("_", "-"), str(value)]
    return shlex.join(words)


def digest(path: str | Path) -> str:
    """Fingerprint of an input: a file's SHA-256, or a folder's listing (names, sizes, mtimes).

    A store in object storage: its root metadata's entity tag and size (the root is written
    last, by every commit: :mod:`pipeline.atomic`).
    """
    location = storage.parse(path)
    if storage.is_url(location):
        return "etag:" + storage.fingerprint(storage.join(location, storage.ROOT))
    path = Path(path)
    h = hashlib.sha256()
    if path.is_file():
        with path.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        return "sha256:" + h.hexdigest()
    for entry in sorted(path.iterdir()):
        if entry.is_file():
            stat = entry.stat()
            h.update(f"{entry.name}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return "listing:" + h.hexdigest()


def provenance(stage: str, params: Any) -> dict[str, Any]:
    """The provenance record written into an output's attrs.

    Besides the parameters it fingerprints the input files and folders (:func:`digest`), so an
    output made from inputs that have changed since is not taken as up to date.
    """
    record = {
        "stage": stage,
        "command": command_line(stage, params),
        "parameters": to_record(params),
        "inputs": {p: digest(p) for p in paths(params, "in")
                   if storage.any_below(storage.parse(p))},
        "version": __version__,
    }
    if hasattr(params, "seed"):
        record["seed"] = params.seed
    return record


def up_to_date(path: str | Path, stage: str, params: Any) -> bool:
    """Whether the store at ``path`` was made by ``stage`` with these parameters and version."""
    from pipeline.stores.groups import stored_attrs

    attrs = stored_attrs(path)  # an unreadable store is not up to date; it will be rebuilt
    return attrs is not None and attrs.get("provenance") == provenance(stage, params)
