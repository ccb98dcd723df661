"""How an output was made: the stage, its parameters, the equivalent command and the version.

Provenance holds nothing that depends on where or when the stage ran (no scheduler, no clock),
so the same parameters give byte-identical stores on every scheduler, and a run can tell that
an existing output is already what was asked for.
"""

from __future__ import annotations

import dataclasses
import shlex
from pathlib import Path
from typing import Any

from pipeline import __version__
from pipeline.params import to_record


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
            words.append("--" + f.name.replace("_", "-"))
        else:
            words += ["--" + f.name.replace("_", "-"), str(value)]
    return shlex.join(words)


def provenance(stage: str, params: Any) -> dict[str, Any]:
    """The provenance record written into an output's attrs."""
    return {
        "stage": stage,
        "command": command_line(stage, params),
        "parameters": to_record(params),
        "version": __version__,
    }


def up_to_date(path: str | Path, stage: str, params: Any) -> bool:
    """Whether the store at ``path`` was made by ``stage`` with these parameters and version."""
    import zarr

    if not (Path(path) / "zarr.json").is_file():
        return False
    try:
        recorded = zarr.open_group(str(path), mode="r").attrs.get("provenance")
    except Exception:  # an unreadable store is not up to date; it will be rebuilt
        return False
    return recorded == provenance(stage, params)
