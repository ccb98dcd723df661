"""Which measured format a path holds, opened as layers, and the colour reading ingest applies.

:func:`open_layers` finds the format of a folder or file from the folder itself or the file's
first bytes (a folder of EXR/PNG images, a UBO2003/ATRIUM zip, a UTIA BIG file) and opens it
as a :class:`~pipeline.layer_sources.LayerSource`; ``btf ingest`` reads it and ``btf inspect``
describes it (a Bonn DFMF ``.btf`` file goes to :mod:`pipeline.dfmf_io` in both).

:func:`colour_note` and :func:`dfmf_colour_note` say in one line how a source's values become
the store's: which decoding or conversion was applied and the option that changes it, so that
nothing is assumed without a word (``btf ingest`` prints the line, ``btf inspect`` shows it).
"""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import BTFError
from pipeline.layer_sources import FolderReader, LayerSource, folder_source
from tasks.transform import DFMF_EPS, DFMF_MODELS

# the colour models' values in a few words (tasks.transform.DFMF_MODELS has the formulas)
DFMF_MODEL_WORDS = {
    0: "RGB, linear", 1: "YUV, linear", 3: "PCA, linear", 4: "YCoCg, linear",
    9: "Y log, U/V linear; YUV to linear RGB", 10: "Y log, U/V signed log; YUV to linear RGB",
    11: "Y log, U/V over Y; YUV to linear RGB", 12: "log of each channel",
}
_DECODED = {"srgb": "decoded from sRGB to linear",
            "gamma2.2": "decoded as (v/max)^2.2 to linear (the Mitsuba BTF plugin's curve)",
            "none": "taken as linear, v/max, not decoded"}


def open_layers(src: str | Path, *, manifest: str | Path | None = None, decode: str = "auto",
                xyz: str = "srgb", hdr_rows: str = "bottom-up") -> LayerSource:
    """The layers of ``src``, its format found from the folder or the file's first bytes.

    ``decode`` ``"auto"`` is ``srgb`` for an archive's JPEGs (and, in
    :func:`~pipeline.layer_sources.folder_source`, for a UTIA folder's PNGs).

    Raises
    ------
    BTFError
        SRC missing, or a file that is neither a zip archive nor a BIG file (by content or by
        its suffix), or whatever the format's reader refuses.
    """
    from pipeline.archive_sources import ZIP_MAGICS, big_source, zip_source
    from tasks.container_formats import BIG_MAGIC

    src = Path(src)
    if src.is_dir():
        return folder_source(src, manifest, decode=decode, xyz=xyz)
    if not src.is_file():
        raise BTFError(f"{src}: no such folder or file")
    if manifest is not None:
        raise BTFError(f"{src}: --manifest is for folders of images; an archive's directions "
                       "come from its member names or its list of directions")
    with src.open("rb") as f:
        magic = f.read(8)
    if magic.startswith(ZIP_MAGICS) or src.suffix.lower() == ".zip":
        return zip_source(src, decode="srgb" if decode == "auto" else decode,
                          hdr_rows=hdr_rows)
    if magic == BIG_MAGIC or src.suffix.lower() == ".big":
        return big_source(src, xyz=xyz)
    raise BTFError(f"{src}: not a folder of images, a zip archive (UBO2003/ATRIUM), a BIG file "
                   "(UTIA) or a .btf file (Bonn DFMF)")


def _display(kind: str, decoding: str) -> str:
    others = " or ".join(d for d in ("srgb", "gamma2.2", "none") if d != decoding)
    return f"{kind} values {_DECODED[decoding]} (--decode {decoding}; --decode {others} to change)"


def _xyz(origin: str, keep: bool) -> str:
    if keep:
        return (f"{origin} stored as X,Y,Z (--xyz keep; --xyz srgb converts them to linear sRGB "
                "primaries, --xyz none reads the channels as named)")
    return (f"{origin} converted to linear sRGB primaries (--xyz keep stores X,Y,Z; --xyz none "
            "reads the channels as named)")


_AS_NAMED = "stored as they are (linear), channels as named (--xyz none: no XYZ conversion; " \
            "--xyz srgb converts XYZ to linear sRGB primaries)"


def _exr(source: LayerSource, reader: FolderReader, xyz: str) -> str:
    if reader.xyz == ("X", "Y", "Z"):
        return _xyz("CIE XYZ (D65)", reader.keep)
    if reader.xyz is not None:
        return _xyz(f"EXR channels {','.join(reader.xyz)} read as CIE XYZ (D65), as UTIA's "
                    "database stores them,", reader.keep)
    utia = source.attrs.get("format", "").startswith("UTIA")
    if xyz == "none" and (utia or set(source.info.channels) == {"X", "Y", "Z"}):
        return f"EXR values {_AS_NAMED}"
    return "EXR values stored as they are (linear)"


def colour_note(source: LayerSource, *, xyz: str = "srgb") -> str:
    """How ``source``'s values become the store's, and the option that changes it (one line).

    ``xyz`` is the ``--xyz`` option the source was opened with. Read from the source's
    reader and attrs: exactly what its reader does to each image.
    """
    from pipeline.archive_sources import BigReader, ZipReader

    reader = source.reader
    if isinstance(reader, ZipReader):
        if str(source.first.key).lower().endswith(".hdr"):
            return "Radiance RGBE values stored as they are (linear, the camera's RGB)"
        return _display("JPEG", reader.decode)
    if isinstance(reader, BigReader):
        if reader.xyz:
            return _xyz("CIE XYZ (the file's colour space)", reader.keep)
        colour = source.attrs.get("colour", "")
        if xyz == "none" and "XYZ" in colour.upper():
            return f"BIG values {_AS_NAMED} ({colour})"
        return f"BIG values {colour.replace('as stored', 'stored as they are')}"
    if isinstance(reader, FolderReader):
        suffixes = {Path(e.key).suffix.lower() for row in source.grid for e in row}
        parts = ([_display("PNG", reader.decode)] if ".png" in suffixes else []) + (
            [_exr(source, reader, xyz)] if ".exr" in suffixes else [])
        return "; ".join(parts)
    return str(source.attrs.get("colour", "as stored"))


def dfmf_colour_note(model: int, *, cosine: bool = False) -> str:
    """What ingest does with a DFMF file's colour model ``model`` (one line)."""
    name, formula = DFMF_MODELS[model]
    words = DFMF_MODEL_WORDS.get(model, formula)
    if name == "linear":
        note = (f"DFMF colour model {model} ({words}) kept as linear values (transform linear)"
                if model == 0 else
                f"DFMF colour model {model} ({words}) folded into U: the store holds linear "
                "RGB (transform linear)")
    else:
        note = (f"DFMF colour model {model} ({words}, eps {DFMF_EPS:g}) kept as the store's "
                f"transform ({name})")
    if cosine:
        note += "; the file's cosine flag is set: values divided by cos(theta_light)"
    return note


def dfmf_readers_note(model: int) -> str:
    """What the common DFMF readers return for colour model ``model`` (one line, for export).

    From their code (docs/formats.md, "Which reader opens what"): btflib decodes every model;
    ``btf.hh`` and btf-extractor (the Mitsuba BTF plugin's reader) decode models 0 and 11
    only, clamp model 11 to [0, 1] and return the channel sums of any other model.
    """
    words = DFMF_MODEL_WORDS.get(model, DFMF_MODELS[model][1])
    if model == 0:
        return (f"colour model 0 ({words}): btflib, btf.hh and btf-extractor (the Mitsuba BTF "
                "plugin's reader) all return the values as they are")
    if model == 11:
        return (f"colour model 11 ({words}): btflib, btf.hh and btf-extractor (the Mitsuba BTF "
                "plugin's reader) decode it, but btf-extractor clamps RGB to [0, 1] (values "
                "above 1 are lost), writes U = a1 Y + eps for btflib's a1 (Y + eps) (up to "
                "2.5e-5 apart) and returns BGR")
    if model == 12:
        return (f"colour model 12 ({words}): btflib decodes it; btf.hh, btf-extractor and the "
                "Mitsuba BTF plugin decode only models 0 and 11 and return this model's "
                "channel sums a without the exp: radiance is exp(a) - "
                f"{DFMF_EPS:g} per channel; or export the layers as EXR for them "
                "(btf export STORE FOLDER)")
    return (f"colour model {model} ({words}): btflib decodes it; btf.hh, btf-extractor and the "
            "Mitsuba BTF plugin decode only models 0 and 11 and return this model's channel "
            "sums undecoded (log Y and U, V, not RGB); export the layers as EXR for them "
            "(btf export STORE FOLDER)")
