"""``btf ingest``: a measured BTF into a store, the format found from SRC itself.

The format is the one entry of :mod:`pipeline.sources` that can open SRC (a folder of EXR or
PNG layers, a UBO2003/ATRIUM zip archive, a UTIA BIG file, a Bonn DFMF ``.btf`` file, ...).
An image format opens it as a :class:`~pipeline.layer_sources.LayerSource`, streamed here
into a radiance store; a format that writes its own store does so (a DFMF file becomes a
compressed store without expansion).

The directions must form a full view x light grid, checked before anything is written (with
the headers of a folder's images; an archive's images are checked against its first one as
they are read). Memory never depends on the size of the input:

- layers that fit one task block whole (up to ``TASK_TEXELS`` a side, so every measured
  archive of 256 x 256 images) are read straight into the store: one task per task block (one
  view, a block of lights) reads its images one by one into the block and writes it;
- larger layers take two passes, so that a task never holds more than one image or one task
  block: one task per image reads it, checks its pixels and stages it in a scratch array of
  one layer per chunk; then one task per block of the final layout copies that block from the
  scratch array (which is removed before the store is published).

Both resume after a kill (:mod:`pipeline.resume`): finished blocks and images are not redone.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np

from pipeline import storage
from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.graphs.blocks import aligned_chunks, store_aligned, store_blocks
from pipeline.images import ImageInfo
from pipeline.layer_sources import XYZ_MODES, LayerSource, ReadOptions
from pipeline.params import ParamError, option
from pipeline.provenance import provenance
from pipeline.resume import Progress
from pipeline.session import Session
from pipeline.sources import FORMATS, formats_help, source_format
from pipeline.stage import Stage
from pipeline.stores.base import RADIANCE, location
from pipeline.stores.radiance import LayoutOptions, create_radiance_store, stored
from tasks.colour import DECODINGS
from tasks.container_formats import ATRIUM_ROWS

STAGING = "_staging"  # scratch array inside the partial store, removed before it is published


@dataclasses.dataclass(frozen=True)
class IngestParams(LayoutOptions):
    """Parameters of ``btf ingest``."""

    src: str = option(help="the measured BTF: one of the formats listed above",
                      positional=True, path="in")
    out: str = option(help="output store (a .zarr directory): radiance, or factors from a DFMF "
                           "file", positional=True,
                      path="out")
    manifest: str | None = option(
        None, path="in", metavar="CSV",
        help="CSV with columns file,theta_light,phi_light,theta_view,phi_view (default: "
             "SRC/manifest.csv if present, else UTIA file names)")
    srgb: bool = option(False, help="decode PNG values from sRGB to linear (the same as "
                                    "--decode srgb)")
    decode: str = option(
        "auto", choices=("auto", *DECODINGS),
        help="how 8/16-bit display-encoded values (JPEG, PNG) become linear: srgb (the sRGB "
             "curve), gamma2.2 ((v/255)^2.2, as the Mitsuba BTF plugin), none (v/255); auto: "
             "srgb for archives' JPEGs and UTIA folders' PNGs, none for other PNG folders")
    xyz: str = option(
        "srgb", choices=XYZ_MODES,
        help="CIE XYZ images (EXRs with X,Y,Z channels, UTIA folders' EXRs, BIG files whose "
             "colour space is XYZ): srgb converts them to linear sRGB primaries (D65), keep "
             "stores X,Y,Z, none reads their channels as named")
    hdr_rows: str = option(
        "bottom-up", choices=ATRIUM_ROWS,
        help="row order of ATRIUM .hdr images, whose header says '+X 256 -Y 256': bottom-up "
             "(their first row is the picture's bottom, as btf-extractor reads them) or "
             "top-down")
    radiance: bool = option(
        False, help="a DFMF file decoded into a radiance store, every layer as Bonn's readers "
                    "decode it (in --dtype), instead of its factors; image formats always "
                    "give radiance")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        self.layout()  # raises ParamError naming the bad option
        if self.srgb and self.decode not in ("auto", "srgb"):
            raise ParamError("srgb", f"--srgb contradicts --decode {self.decode}; give one")

    def decoding(self) -> str:
        """The ``--decode`` asked for, ``--srgb`` being ``srgb``; ``auto`` left to the format."""
        return "srgb" if self.srgb else self.decode

    def read_options(self) -> ReadOptions:
        """How the source's values are read (its format uses the options that apply to it)."""
        return ReadOptions(manifest=self.manifest, decode=self.decoding(), xyz=self.xyz,
                           hdr_rows=self.hdr_rows)


def _task_key(key):
    # a folder's image paths go to tasks as absolute locations (workers may run elsewhere)
    return location(key) if isinstance(key, Path) else key


def _checked(reader, key, info: ImageInfo, first: str) -> np.ndarray:
    """The pixels of image ``key``, refused unless of ``info``'s shape and finite."""
    pixels = reader(key)
    where = reader.where(key)
    shape = (info.height, info.width, len(info.channels))
    if pixels.shape != shape:
        raise BTFError(f"{where}: image of {pixels.shape[0]}x{pixels.shape[1]} with "
                       f"{pixels.shape[2]} channel(s), but {first} is {shape[0]}x{shape[1]} "
                       f"with {shape[2]}: every image must have the first one's size")
    if not np.isfinite(pixels).all():
        bad = ~np.isfinite(pixels)
        y, x, c = np.argwhere(bad)[0]
        raise BTFError(f"{where}: {int(bad.sum())} non-finite pixel value(s) (NaN or Inf), "
                       f"the first at y={y}, x={x}, channel {info.channels[c]}")
    return pixels


def _stage_image(store: str, view: int, light: int, reader, key, *, info: ImageInfo,
                 first: str) -> None:
    import zarr

    target = zarr.open_array(storage.store(store), path=STAGING, mode="r+")
    pixels = _checked(reader, key, info, first)
    target[view, light] = stored(pixels, target.dtype, reader.where(key))


def _read_block(reader, keys: list, *, info: ImageInfo, first: str,
                dtype: str = "float32") -> np.ndarray:
    """The images of one view and a block of lights, ``(1, lights, height, width, channels)``.

    In the store's ``dtype`` (:func:`~pipeline.stores.radiance.stored`).
    """
    block = np.empty((1, len(keys), info.height, info.width, len(info.channels)), dtype)
    for i, key in enumerate(keys):
        block[0, i] = stored(_checked(reader, key, info, first), block.dtype, reader.where(key))
    return block


def _whole_images(radiance) -> bool:
    """Whether a task block of ``radiance`` holds its layers whole (one block in y and x)."""
    return all(len(c) == 1 for c in aligned_chunks(radiance)[2:4])


def _image_blocks(source: LayerSource, radiance):
    """``radiance``'s task blocks and the reading of each: ``make(index)`` for its images.

    For :func:`~pipeline.graphs.blocks.store_blocks`: block ``(v, b, 0, 0, 0)`` holds view
    ``v``'s lights of light block ``b``, read by :func:`_read_block`.
    """
    info, first = source.info, source.first.name
    chunks = aligned_chunks(radiance)
    starts = np.cumsum((0, *chunks[1]))

    def make(index):
        view, block = index[0], index[1]
        keys = [_task_key(e.key) for e in source.grid[view][starts[block]:starts[block + 1]]]
        return functools.partial(_read_block, source.reader, keys, info=info, first=first,
                                 dtype=str(radiance.dtype))

    return chunks, make


def _staged(source: LayerSource, group, tmp, progress: Progress, session: Session) -> None:
    """Images too large for one task block: staged one per task, then copied in blocks."""
    import dask
    import dask.array as da

    radiance, first = group[RADIANCE], source.first.name
    stage = [(f"image/{v}.{li}", dask.delayed(_stage_image, pure=True)(
                 location(tmp), v, li, source.reader, _task_key(e.key), info=source.info,
                 first=first))
             for v, row in enumerate(source.grid) for li, e in enumerate(row)]
    progress.distrust_damaged(lambda line: session.log(f"ingest: {line}"), only=(STAGING,))
    todo, _ = progress.pending(stage)
    session.compute(*todo)
    staged = da.from_zarr(group[STAGING], chunks=aligned_chunks(radiance))
    session.compute(store_aligned([staged], [radiance], progress=progress))
    storage.remove(storage.join(location(tmp), STAGING))  # with its folder keys


def ingest(params: IngestParams, session: Session) -> Path:
    """Ingest the measurement described by ``params`` into a store; returns its path.

    The format of ``params.src`` (:func:`pipeline.sources.source_format`) writes its own store
    or opens the source's layers. Layers that fit a task block whole (up to ``TASK_TEXELS`` a
    side) are read straight into the task blocks of a radiance store, one pass; larger ones go
    through the scratch array.
    """
    found = source_format(params.src)
    if found.ingest is not None:  # a format that is not layers (a DFMF file's factors)
        return found.ingest(params, session)
    source = found.open(Path(params.src), params.read_options())
    directions, info = source.directions, source.info
    attrs = {"source": "ingest", "ingest": source.attrs,
             "provenance": provenance("ingest", params)}
    layout = params.layout(dtype=info.precision)  # 8-bit and half: float16 holds them
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"]) as tmp:
        def create():
            made = create_radiance_store(tmp, directions=directions, ny=info.height,
                                         nx=info.width, channels=info.channels,
                                         layout=layout, attrs=attrs)
            target = made[RADIANCE]
            if not _whole_images(target):
                made.create_array(
                    STAGING, shape=target.shape, dtype=target.dtype, fill_value=np.nan,
                    chunks=(1, 1, *target.chunks[2:]), compressors=target.compressors)
            return made

        progress = Progress(tmp)
        group = progress.skeleton(create)
        radiance = group[RADIANCE]
        session.log(f"ingest: {directions.views} x {directions.lights} layers of "
                    f"{info.height} x {info.width} texels ({','.join(info.channels)}) -> "
                    f"{params.out}")
        session.log(f"ingest: colour: {source.colour_note}")
        session.log(f"ingest: stored as {layout.dtype} ({info.sample} samples"
                    + ("" if params.dtype else "; --dtype changes it") + ")")
        if progress.count():
            session.log(f"ingest: resuming: {progress.count()} images and blocks already "
                        "written")
        if _whole_images(radiance):
            # no chunk of measured radiance is all fill value (NaN is refused), so zarr's check
            # for empty chunks is skipped: measured 20% faster writes of 256^2 layers
            target = radiance.with_config({"write_empty_chunks": True})
            session.compute(store_blocks(target, *_image_blocks(source, radiance),
                                         progress=progress))
        elif STAGING in group:  # else a killed run had finished with it
            _staged(source, group, tmp, progress, session)
    return Path(params.out)


STAGE = Stage("ingest", IngestParams, ingest,
              f"read measured BTFs ({', '.join(FORMATS)}) into a store",
              "Read a measured BTF into a store; the format comes from SRC (its name or first "
              "bytes), one of:\n" + formats_help() + "\nImage formats become a radiance store, "
              "streamed a block of directions at a time. See docs/formats.md.",
              makes_store=True, whole="a measurement: the stages after it read all of it")
