"""``btf export``: layers of a store as EXR or PNG files, or a compressed store as a DFMF file.

Exported files are named after their directions and listed with their exact angles in
``manifest.csv`` (:mod:`pipeline.layer_files`), so exporting to EXR and ingesting again gives
back the same float32 values and directions. PNG files are tone-mapped with one exposure for
all layers (from thumbnails of a few of them), so they stay comparable. An output named
``*.btf`` is a Bonn DFMF file of a compressed store, for renderers (:mod:`pipeline.dfmf_io`).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.graphs.blocks import read_chunks
from pipeline.graphs.thumbnails import thumbnail
from pipeline.images import write_exr, write_png
from pipeline.layer_files import layer_name, write_manifest
from pipeline.params import ParamError, option
from pipeline.session import Session
from pipeline.stage import Stage
from pipeline.stores import CompressedStore, RadianceStore, open_layers, open_store
from pipeline.stores.base import layer_indices, location, read_channels
from pipeline.stores.radiance import as_float32
from tasks.svd import reconstruct_layers
from tasks.tonemap import exposure, to_uint8, tonemap

# Layers one export task holds at most: a whole stored light block if it fits (each chunk is
# decoded once), else fewer (big layers: chunks are decoded once per task that needs them).
TASK_BUDGET = 256 << 20


@dataclasses.dataclass(frozen=True)
class ExportParams:
    """Parameters of ``btf export``."""

    store: str = option(help="radiance or compressed store to export from", positional=True,
                        path="in")
    out_dir: str = option(help="folder to write the layers and manifest.csv to, or a .btf "
                               "file: a compressed store as a Bonn DFMF file for renderers",
                          positional=True, path="out")
    light: tuple[int, ...] | None = option(None, metavar="I,..", repeatable=True,
                                           help="light indices to export (default: all)")
    view: tuple[int, ...] | None = option(None, metavar="J,..", repeatable=True,
                                          help="view indices to export (default: all)")
    format: str = option("exr", choices=("exr", "png"),
                         help="exr: radiance values; png: tone-mapped 8-bit sRGB previews")
    half: bool = option(False, help="write EXR (or a .btf file's factors) as half floats "
                                    "instead of float32")
    exposure: float | None = option(None, help="PNG exposure scale (default: automatic, one "
                                               "scale for all layers)")
    overwrite: bool = option(False, record=False, help="replace OUT_DIR if it exists")

    def __post_init__(self):
        if self.dfmf:
            for name in ("light", "view", "exposure"):
                if getattr(self, name) is not None:
                    raise ParamError(name, "does not apply to a .btf file (it holds every "
                                           "layer, as factors)")
            return
        if self.half and self.format != "exr":
            raise ParamError("half", "only applies to --format exr")
        if self.exposure is not None and self.format != "png":
            raise ParamError("exposure", "only applies to --format png (EXR keeps the values)")
        if self.exposure is not None and not self.exposure > 0:
            raise ParamError("exposure", f"must be positive, got {self.exposure}")

    @property
    def dfmf(self) -> bool:
        """Whether the output is a Bonn DFMF ``.btf`` file."""
        return self.out_dir.lower().endswith(".btf")


def _sample_exposure(store: str, layers: list[tuple[int, int]], session: Session) -> float:
    """One exposure for a set of layers, from thumbnails of at most 8 of them."""
    import dask.array as da

    ds = open_layers(store, read_chunks)  # radiance, or a compressed store rebuilt (xarray)
    pick = layers[:: max(1, math.ceil(len(layers) / 8))]
    (values,) = session.compute(da.stack([thumbnail(ds, v, li, 128) for v, li in pick]))
    return exposure(values)


def _layers(store: str, view: int, lights: list[int]) -> np.ndarray:
    """Layers ``(light, y, x, channel)`` of a radiance store, or rebuilt from a compressed one.

    A compressed store's layers need its whole ``V``: one task holds it once for its lights.
    """
    source = open_store(store, RadianceStore, CompressedStore, checked=False)
    if isinstance(source, RadianceStore):
        return as_float32(source.radiance.get_orthogonal_selection((view, lights)))
    group = source.group
    u = group["U"].get_orthogonal_selection((view, lights))
    transform = source.transform
    return reconstruct_layers(u, group["S"][:], as_float32(group["V"][:]), transform=transform,
                              scale=transform.layer_scale(group["theta_light"][lights]))


def _export_block(store: str, out: str, view: int, lights: list[int], names: list[str], *,
                  channels: tuple[str, ...], fmt: str, half: bool, scale: float) -> None:
    block = _layers(store, view, lights)
    for pixels, name in zip(block, names, strict=True):
        if fmt == "exr":
            write_exr(Path(out) / name, pixels, channels, half=half)
        else:
            image = to_uint8(tonemap(pixels, scale=scale))
            write_png(Path(out) / name, image[..., 0] if image.shape[-1] == 1 else image)


def export(params: ExportParams, session: Session) -> Path:
    """Write the selected layers of a store as image files plus ``manifest.csv``."""
    if params.dfmf:
        from pipeline.dfmf_io import export_dfmf

        return export_dfmf(params.store, params.out_dir, half=params.half,
                           overwrite=params.overwrite, session=session)
    import dask

    # planned from the store's own arrays: no Dataset (xarray: 0.6-0.7 s of a process)
    source = open_store(params.store, RadianceStore, CompressedStore)
    d = source.directions
    views = layer_indices(params.view, d.theta_view.size, "view", params.store)
    lights = layer_indices(params.light, d.theta_light.size, "light", params.store)
    channels = read_channels(source.group)
    scale = params.exposure or 1.0
    if params.format == "png" and params.exposure is None:
        scale = _sample_exposure(params.store, [(v, li) for v in views for li in lights],
                                 session)
    # lights per stored chunk (and shard) of a radiance store, per block of a compressed
    # store's U: each is read once
    block = (source.radiance.chunks[1] if isinstance(source, RadianceStore)
             else read_chunks(source.group, "U")["light"])
    layer_bytes = 4 * int(np.prod(source.shape[2:]))  # a task's layers are float32
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


STAGE = Stage("export", ExportParams, export,
              "write layers as EXR/PNG files, or a compressed store as a Bonn .btf file",
              "Write the selected layers of a radiance or compressed store as EXR (exact "
              "float32, or --half) or tone-mapped PNG, named by their directions, with a "
              "manifest.csv that btf ingest reads back. An OUT ending in .btf gets a compressed "
              "store as a Bonn DFMF file for renderers (btflib, btf-extractor, Mitsuba's BTF "
              "plugin): each channel at its own rank, float32 (exact) or --half.")
