"""``btf ingest``: a folder of EXR or PNG layers into a radiance store.

A Bonn DFMF ``.btf`` file becomes a compressed store instead (:mod:`pipeline.dfmf_io`).

The directions of each image come from a manifest CSV (``file,theta_light,phi_light,
theta_view,phi_view``; ``SRC/manifest.csv`` is used when present) or from UTIA file names
``tl{theta}_pl{phi}_tv{theta}_pv{phi}.{exr,png}``. Every image's header is checked before
anything is written (readable, same size and channels as the others, angles on the hemisphere,
no duplicate directions, every view x light combination present).

Then the images are written in two passes, so that memory never depends on the folder or on
the chunking: one task per image reads it, checks its pixels and stages it in a scratch array
of one layer per chunk; then one task per block of the final layout copies that block from the
scratch array. A task holds one image (image decoders read whole files) or one task block.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np

from pipeline import storage
from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.graphs.blocks import aligned_chunks, store_aligned
from pipeline.images import IMAGE_SUFFIXES, ImageInfo, image_info, read_image
from pipeline.layer_files import MANIFEST, MANIFEST_COLUMNS, UTIA_NAME
from pipeline.params import option
from pipeline.provenance import provenance
from pipeline.resume import Progress
from pipeline.session import Session
from pipeline.stores.base import RADIANCE, Directions, location
from pipeline.stores.radiance import Layout, create_radiance_store
from tasks.sampling import canonical_direction

STAGING = "_staging"  # scratch array inside the partial store, removed before it is published


@dataclasses.dataclass(frozen=True)
class IngestParams:
    """Parameters of ``btf ingest``."""

    src: str = option(help="folder of EXR or PNG layers", positional=True, path="in")
    out: str = option(help="output radiance store (a .zarr directory)", positional=True,
                      path="out")
    manifest: str | None = option(
        None, path="in", metavar="CSV",
        help="CSV with columns file,theta_light,phi_light,theta_view,phi_view (default: "
             "SRC/manifest.csv if present, else UTIA file names)")
    srgb: bool = option(False, help="decode PNG values from sRGB to linear")
    chunk: int = option(128, help="texels per side of a stored chunk")
    dir_chunk: int = option(16, help="light directions per stored chunk")
    shard: int = option(0, help="texels per side of a shard file grouping several chunks (a "
                                "multiple of --chunk); 0: one file per chunk")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        self.layout()  # raises ParamError naming the bad option

    def layout(self) -> Layout:
        """The store layout these parameters ask for."""
        return Layout(chunk=self.chunk, dir_chunk=self.dir_chunk, shard=self.shard)


@dataclasses.dataclass(frozen=True)
class Entry:
    """One image and its directions ``(theta_light, phi_light, theta_view, phi_view)``."""

    path: Path
    angles: tuple[float, float, float, float]
    origin: str  # where the directions came from, for messages


def _angle(text: str, where: str, column: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise BTFError(f"{where}: {column} {text!r} is not a number") from None
    if not np.isfinite(value):
        raise BTFError(f"{where}: {column} {text!r} is not finite")
    if column.startswith("theta") and not 0 <= value <= 90:
        raise BTFError(f"{where}: {column} {value:g} is outside 0-90 degrees (the hemisphere)")
    return value


def _from_manifest(src: Path, manifest: Path) -> list[Entry]:
    if not manifest.is_file():
        raise BTFError(f"{manifest}: manifest not found")
    with manifest.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = set(MANIFEST_COLUMNS) - set(reader.fieldnames or ())
        if missing:
            raise BTFError(f"{manifest}: missing column(s) {', '.join(sorted(missing))}; "
                           f"expected {','.join(MANIFEST_COLUMNS)}")
        entries = []
        for row in reader:
            where = f"{manifest}:{reader.line_num}"
            path = Path(row["file"]) if Path(row["file"]).is_absolute() else src / row["file"]
            if not path.is_file():
                raise BTFError(f"{where}: file {row['file']!r} not found in {src}")
            angles = tuple(_angle(row[c], where, c) for c in MANIFEST_COLUMNS[1:])
            entries.append(Entry(path, angles, where))
    return entries


def _from_names(src: Path) -> list[Entry]:
    entries = []
    for path in sorted(p for p in src.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES):
        match = UTIA_NAME.fullmatch(path.name)
        if match is None:
            raise BTFError(f"{path}: name does not follow tl{{theta}}_pl{{phi}}_tv{{theta}}_"
                           "pv{phi}.exr|png; name the files so or give a --manifest")
        angles = tuple(_angle(g, str(path), c)
                       for g, c in zip(match.groups()[:4], MANIFEST_COLUMNS[1:], strict=True))
        entries.append(Entry(path, angles, str(path)))
    return entries


def _axis(values: list[tuple[float, float]], *, ordered: bool) -> list[tuple[float, float]]:
    unique = list(dict.fromkeys(values))
    return unique if ordered else sorted(unique)


def find_layers(src: str | Path, manifest: str | Path | None = None
                ) -> tuple[Directions, list[list[Entry]]]:
    """Directions of a folder of layers and its images as a ``[view][light]`` grid.

    Raises
    ------
    BTFError
        Naming the file: no images, a manifest row naming a missing file, an unparsable name,
        two images with the same directions, or a view x light combination without an image.
    """
    src = Path(src)
    if not src.is_dir():
        raise BTFError(f"{src}: not a folder")
    if manifest is None and (src / MANIFEST).is_file():
        manifest = src / MANIFEST
    entries = _from_manifest(src, Path(manifest)) if manifest else _from_names(src)
    if not entries:
        raise BTFError(f"{src}: no .exr or .png images found")
    seen: dict[tuple[float, ...], Entry] = {}
    for e in entries:
        key = (*canonical_direction(*e.angles[:2]), *canonical_direction(*e.angles[2:]))
        if key in seen:
            raise BTFError(f"{e.origin}: {e.path.name} has the same directions as "
                           f"{seen[key].path.name} (light {key[0]:g}/{key[1]:g}, "
                           f"view {key[2]:g}/{key[3]:g} degrees)")
        seen[key] = e
    ordered = manifest is not None
    lights = _axis([k[:2] for k in seen], ordered=ordered)
    views = _axis([k[2:] for k in seen], ordered=ordered)
    grid = []
    for v in views:
        row = []
        for light in lights:
            entry = seen.get((*light, *v))
            if entry is None:
                raise BTFError(f"{src}: no image for light {light[0]:g}/{light[1]:g} and view "
                               f"{v[0]:g}/{v[1]:g} degrees (theta/phi); a BTF needs every view "
                               f"x light combination ({len(seen)} of "
                               f"{len(views) * len(lights)} present)")
            row.append(entry)
        grid.append(row)
    directions = Directions(*(np.array(a, np.float64) for a in
                              ([v[0] for v in views], [v[1] for v in views],
                               [light[0] for light in lights], [light[1] for light in lights])))
    return directions, grid


def check_headers(grid: list[list[Entry]]) -> ImageInfo:
    """Read every header; all images must have the first one's size and channels."""
    first = None
    for entry in (e for row in grid for e in row):
        info = image_info(entry.path)
        if first is None:
            first, first_path = info, entry.path
        elif info != first:
            raise BTFError(f"{entry.path}: {info.height}x{info.width} with channels "
                           f"{','.join(info.channels)}, but {first_path.name} is "
                           f"{first.height}x{first.width} with {','.join(first.channels)}")
    return first


def _stage_image(store: str, view: int, light: int, path: str, *, srgb: bool,
                 info: ImageInfo) -> None:
    import zarr

    pixels, _ = read_image(path, srgb=srgb)
    shape = (info.height, info.width, len(info.channels))
    if pixels.shape != shape:
        raise BTFError(f"{path}: pixels of shape {pixels.shape}, expected {shape}")
    bad = ~np.isfinite(pixels)
    if bad.any():
        y, x, c = np.argwhere(bad)[0]
        raise BTFError(f"{path}: {int(bad.sum())} non-finite pixel value(s) (NaN or Inf), "
                       f"the first at y={y}, x={x}, channel {info.channels[c]}")
    zarr.open_array(storage.store(store), path=STAGING, mode="r+")[view, light] = pixels


def ingest(params: IngestParams, session: Session) -> Path:
    """Ingest the folder described by ``params`` into a radiance store; returns its path."""
    if Path(params.src).suffix.lower() == ".btf":
        from pipeline.dfmf_io import ingest_dfmf
        return ingest_dfmf(params, session)
    import dask
    import dask.array as da

    directions, grid = find_layers(params.src, params.manifest)
    info = check_headers(grid)
    attrs = {"btf_kind": directions.kind, "source": "ingest",
             "provenance": provenance("ingest", params)}
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"]) as tmp:
        def create():
            made = create_radiance_store(tmp, directions=directions, ny=info.height,
                                         nx=info.width, channels=info.channels,
                                         layout=params.layout(), attrs=attrs)
            target = made[RADIANCE]
            made.create_array(
                STAGING, shape=target.shape, dtype="float32", fill_value=np.nan,
                chunks=(1, 1, *target.chunks[2:]), compressors=target.compressors)
            return made

        progress = Progress(tmp)
        group = progress.skeleton(create)
        radiance = group[RADIANCE]
        stage = [(f"image/{v}.{li}", dask.delayed(_stage_image, pure=True)(
                     location(tmp), v, li, location(e.path), srgb=params.srgb, info=info))
                 for v, row in enumerate(grid) for li, e in enumerate(row)]
        session.log(f"ingest: {len(grid)} x {len(grid[0])} layers of {info.height} x "
                    f"{info.width} texels ({','.join(info.channels)}) -> {params.out}")
        if progress.count():
            session.log(f"ingest: resuming: {progress.count()} images and blocks already "
                        "written")
        if STAGING in group:  # else a killed run had finished with it
            todo, _ = progress.pending(stage)
            session.compute(*todo)
            staged = da.from_zarr(group[STAGING], chunks=aligned_chunks(radiance))
            session.compute(store_aligned([staged], [radiance], progress=progress))
            storage.remove(storage.join(location(tmp), STAGING))  # with its folder keys
    return Path(params.out)
