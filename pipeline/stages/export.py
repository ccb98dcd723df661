"""``btf export``: layers of a store as EXR or PNG files.

Exported files are named after their directions and listed with their exact angles in
``manifest.csv`` (:mod:`pipeline.layer_files`), so exporting to EXR and ingesting again gives
back the same float32 values and directions. PNG files are tone-mapped with one exposure for
all layers (from thumbnails of a few of them), so they stay comparable.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from pipeline import storage
from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.graphs.thumbnails import thumbnail
from pipeline.images import write_exr, write_png
from pipeline.layer_files import layer_name, write_manifest
from pipeline.params import ParamError, option
from pipeline.session import Session
from pipeline.stores.base import RADIANCE, Directions, layer_indices, location
from pipeline.stores.radiance import open_radiance
from tasks.tonemap import exposure, to_uint8, tonemap

# Layers one export task holds at most: a whole stored light block if it fits (each chunk is
# decoded once), else fewer (big layers: chunks are decoded once per task that needs them).
TASK_BUDGET = 256 << 20


@dataclasses.dataclass(frozen=True)
class ExportParams:
    """Parameters of ``btf export``."""

    store: str = option(help="radiance store to export from", positional=True, path="in")
    out_dir: str = option(help="folder to write the layers and manifest.csv to",
                          positional=True, path="out")
    light: tuple[int, ...] | None = option(None, metavar="I,..",
                                           help="light indices to export (default: all)")
    view: tuple[int, ...] | None = option(None, metavar="J,..",
                                          help="view indices to export (default: all)")
    format: str = option("exr", choices=("exr", "png"),
                         help="exr: radiance values; png: tone-mapped 8-bit sRGB previews")
    half: bool = option(False, help="write EXR as half floats instead of float32")
    exposure: float | None = option(None, help="PNG exposure scale (default: automatic, one "
                                               "scale for all layers)")
    overwrite: bool = option(False, record=False, help="replace OUT_DIR if it exists")

    def __post_init__(self):
        if self.half and self.format != "exr":
            raise ParamError("half", "only applies to --format exr")
        if self.exposure is not None and self.format != "png":
            raise ParamError("exposure", "only applies to --format png (EXR keeps the values)")
        if self.exposure is not None and not self.exposure > 0:
            raise ParamError("exposure", f"must be positive, got {self.exposure}")


def _sample_exposure(ds, layers: list[tuple[int, int]], session: Session) -> float:
    """One exposure for a set of layers, from thumbnails of at most 8 of them."""
    import dask.array as da

    pick = layers[:: max(1, math.ceil(len(layers) / 8))]
    (values,) = session.compute(da.stack([thumbnail(ds, v, li, 128) for v, li in pick]))
    return exposure(values)


def _export_block(store: str, out: str, view: int, lights: list[int], names: list[str], *,
                  channels: tuple[str, ...], fmt: str, half: bool, scale: float) -> None:
    import zarr

    array = zarr.open_array(storage.store(store), path=RADIANCE, mode="r")
    block = array.get_orthogonal_selection((view, lights))
    for pixels, name in zip(block, names, strict=True):
        if fmt == "exr":
            write_exr(Path(out) / name, pixels, channels, half=half)
        else:
            image = to_uint8(tonemap(pixels, scale=scale))
            write_png(Path(out) / name, image[..., 0] if image.shape[-1] == 1 else image)


def export(params: ExportParams, session: Session) -> Path:
    """Write the selected layers of a store as image files plus ``manifest.csv``."""
    import dask

    ds = open_radiance(params.store)
    d = Directions.of(ds)
    views = layer_indices(params.view, d.theta_view.size, "view", params.store)
    lights = layer_indices(params.light, d.theta_light.size, "light", params.store)
    channels = tuple(str(c) for c in ds["channel"].values)
    scale = params.exposure or 1.0
    if params.format == "png" and params.exposure is None:
        scale = _sample_exposure(ds, [(v, li) for v in views for li in lights], session)
    block = ds[RADIANCE].encoding["chunks"][1]  # lights per stored chunk (and shard)
    layer_bytes = ds[RADIANCE][0, 0].nbytes
    per_task = max(1, min(block, TASK_BUDGET // max(layer_bytes, 1)))
    with atomic_output(params.out_dir, directory=True, overwrite=params.overwrite) as tmp:
        tmp.mkdir()
        rows, writes = [], []
        groups: dict[int, list[int]] = {}  # lights by stored block: each block is read once
        for li in lights:
            groups.setdefault(li // block, []).append(li)
        tasks = [g[k : k + per_task] for g in groups.values() for k in range(0, len(g), per_task)]
        for v in views:
            for members in tasks:
                names = [layer_name(d.theta_light[li], d.phi_light[li], d.theta_view[v],
                                    d.phi_view[v], params.format) for li in members]
                rows += [(n, d.theta_light[li], d.phi_light[li], d.theta_view[v], d.phi_view[v])
                         for n, li in zip(names, members, strict=True)]
                writes.append(dask.delayed(_export_block, pure=True)(
                    location(params.store), location(tmp), v, members, names,
                    channels=channels, fmt=params.format, half=params.half, scale=scale))
        if len({r[0] for r in rows}) != len(rows):
            raise BTFError(f"{params.store}: two layers round to the same file name")
        write_manifest(tmp, rows)
        session.log(f"export: {len(rows)} layers as {params.format.upper()} -> "
                    f"{params.out_dir}")
        session.compute(*writes)
    return Path(params.out_dir)
