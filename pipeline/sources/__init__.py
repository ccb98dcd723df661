"""The measured formats ``btf ingest`` reads and ``btf inspect`` describes: one module each.

Each module of this package declares one input format, ``FORMAT = SourceFormat(...)``, as
xarray's backends declare a ``BackendEntrypoint``: its name, a line of description, whether it
can open a path (``guess_can_open``: by the suffix or the first bytes, cheap), how to open it
and what ``btf inspect`` says of it. An image format (one image per view and light) opens a
path as a :class:`~pipeline.layer_sources.LayerSource`, which ``btf ingest`` streams into a
radiance store; a format that is not images makes its own store instead (``ingest``: a Bonn
DFMF file becomes a compressed store without expansion).

This package finds the declarations itself, as :mod:`pipeline.stages` finds the stages: a new
module with a ``FORMAT`` is a new format, with no list to edit. :data:`ORDER` only says where
the known ones appear in help and messages; others follow, by name. :func:`source_format`
picks the one format that can open a path, refusing a path none or several can open.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.declarations import collect
from pipeline.errors import BTFError

if TYPE_CHECKING:
    from pipeline.layer_sources import LayerSource, ReadOptions

ORDER = ("folder", "zip", "big", "dfmf")


@dataclasses.dataclass(frozen=True)
class SourceFormat:
    """An input format: a module of :mod:`pipeline.sources` declares one as ``FORMAT``.

    Attributes
    ----------
    name
        A short name (the module's), for help and the tests.
    description
        One line for ``btf ingest --help`` and ``btf inspect --help``: what it is, what it
        becomes.
    noun
        What it is in the message for a path no format opens ("a zip archive (UBO2003/ATRIUM)").
    guess_can_open
        ``guess_can_open(path) -> bool``: whether ``path`` is of this format, from its suffix
        or its first bytes, without reading more; a missing path may be claimed by its suffix
        alone (its reader then says it is missing).
    suffixes
        The suffixes (lower case, with the dot) that name this format: of several formats
        that can open a path, the one its name says is taken.
    describe
        ``describe(path) -> dict``: what ``btf inspect`` reports of it from its headers
        (format, size, texels, channels, directions, the colour line, the store ingest would
        make), without decoding more than one image.
    lines
        ``lines(report) -> list[str]``: the text of that report.
    open
        ``open(path, options) -> LayerSource`` for an image format
        (:class:`~pipeline.layer_sources.ReadOptions`): the layers ``btf ingest`` streams into
        a radiance store.
    ingest
        ``ingest(params, session) -> Path`` for a format that writes its own store from
        ``btf ingest``'s parameters, instead of ``open``.
    """

    name: str
    description: str
    noun: str
    guess_can_open: Callable[[Path], bool]
    describe: Callable[[Path], dict[str, Any]]
    lines: Callable[[dict[str, Any]], list[str]]
    suffixes: tuple[str, ...] = ()
    open: Callable[[Path, ReadOptions], LayerSource] | None = None
    ingest: Callable[[Any, Any], Path] | None = None

    def __post_init__(self):
        if (self.open is None) == (self.ingest is None):
            raise TypeError(f"format {self.name!r}: give exactly one of open and ingest")


def _declarations() -> dict[str, SourceFormat]:
    return collect(__name__, __path__, "FORMAT", SourceFormat, ORDER)


def __getattr__(name: str):
    if name == "FORMATS":  # every format, imported once, on first use
        if "FORMATS" not in globals():
            globals()["FORMATS"] = _declarations()
        return globals()["FORMATS"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _either(nouns: list[str], last: str) -> str:
    return ", ".join(nouns[:-1]) + f" {last} " + nouns[-1] if len(nouns) > 1 else nouns[0]


def source_format(path: str | Path) -> SourceFormat:
    """The one format that can open ``path`` (``guess_can_open``).

    Where several can (a zip's first bytes, another format's name), the one whose
    ``suffixes`` name the path is taken.

    Raises
    ------
    BTFError
        Naming the path: missing (and claimed by no format), of no known format, or claimed
        by several of which none or several are named by its suffix.
    """
    path = Path(path)
    formats = list(__getattr__("FORMATS").values())
    found = [f for f in formats if f.guess_can_open(path)]
    if len(found) > 1:
        named = [f for f in found if path.suffix.lower() in f.suffixes]
        found = named if len(named) == 1 else found
    if len(found) == 1:
        return found[0]
    if found:
        raise BTFError(f"{path}: could be {_either([f.noun for f in found], 'or')} (by its "
                       "name or its first bytes); btf cannot tell which: give it the suffix "
                       "of the one it is")
    if not path.is_dir() and not path.is_file():
        raise BTFError(f"{path}: no such folder or file")
    raise BTFError(f"{path}: not {_either([f.noun for f in formats], 'or')}")


def describe_source(path: str | Path) -> dict[str, Any]:
    """The report of a measured source: format, size, directions, colour, what ingest makes.

    Raises
    ------
    BTFError
        Naming the file: a missing path, a file of no known format, a corrupt header (what
        the format's reader refuses).
    """
    path = Path(path)
    if not path.exists():
        raise BTFError(f"{path}: no such file, folder or store")
    return {"path": str(path), "kind": "source", **source_format(path).describe(path)}


def format_source(report: dict[str, Any]) -> str:
    """Human-readable text of a :func:`describe_source` report.

    The format is found again from the report's path (a look at its name and first bytes).
    """
    return "\n".join(source_format(report["path"]).lines(report))


def formats_help(width: int = 92) -> str:
    """The formats as lines for ``--help``: the name and description of each, wrapped."""
    import textwrap

    return "\n".join(textwrap.fill(f.description, width, initial_indent=f"  {f.name:<7} ",
                                   subsequent_indent=" " * 10)
                     for f in __getattr__("FORMATS").values())


__all__ = ["FORMATS", "ORDER", "SourceFormat", "describe_source", "format_source",
           "formats_help", "source_format"]
