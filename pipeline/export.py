"""``btf export`` (layers as EXR or PNG files) and ``btf preview`` (a contact sheet).

Exported files are named after their directions (``tl{theta}_pl{phi}_tv{theta}_pv{phi}``, the
UTIA naming that ``btf ingest`` reads) and listed with their exact angles in ``manifest.csv``,
so exporting to EXR and ingesting again gives back the same float32 values and directions. PNG
files and previews are tone-mapped with one exposure for all layers, so they stay comparable.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.images import write_exr, write_png
from pipeline.params import ParamError, option
from pipeline.runtime import Session
from pipeline.store import RADIANCE, Directions, location, open_radiance
from tasks.sampling import spread_pairs
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


@dataclasses.dataclass(frozen=True)
class PreviewParams:
    """Parameters of ``btf preview``."""

    store: str = option(help="radiance store to preview", positional=True, path="in")
    out: str = option(help="PNG file for the contact sheet", positional=True, path="out")
    count: int = option(12, help="number of layers on the sheet, spread over the directions")
    size: int = option(256, help="largest side of each thumbnail in pixels")
    exposure: float | None = option(None, help="exposure scale (default: automatic)")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        if not 1 <= self.count <= 64:
            raise ParamError("count", f"must be between 1 and 64, got {self.count}")
        if self.size < 16:
            raise ParamError("size", f"must be at least 16 pixels, got {self.size}")


def layer_name(theta_light, phi_light, theta_view, phi_view, suffix: str) -> str:
    """UTIA-style file name of a layer (angles to 4 decimals, trailing zeros dropped)."""
    def fmt(a: float) -> str:
        return f"{a:.4f}".rstrip("0").rstrip(".")

    return (f"tl{fmt(theta_light)}_pl{fmt(phi_light)}_tv{fmt(theta_view)}_"
            f"pv{fmt(phi_view)}.{suffix}")


def layer_indices(selection, size: int, what: str, store: str) -> list[int]:
    """Validated, de-duplicated view or light indices (all of them when ``selection`` is None)."""
    if selection is None:
        return list(range(size))
    bad = [i for i in selection if not 0 <= i < size]
    if bad:
        raise BTFError(f"{store}: --{what} {bad[0]} is out of range (the store has {size} "
                       f"{what}s, indices 0 to {size - 1})")
    return list(dict.fromkeys(selection))


def _thumbnail(ds, view: int, light: int, size: int):
    """A layer averaged down to at most ``size`` texels a side (lazy; no aliasing)."""
    layer = ds[RADIANCE].isel(view=view, light=light)
    factor = max(1, math.ceil(max(layer.sizes["y"], layer.sizes["x"]) / size))
    if factor == 1:
        return layer.data
    return layer.coarsen(y=factor, x=factor, boundary="trim").mean().data


def _sample_exposure(ds, layers: list[tuple[int, int]], session: Session) -> float:
    """One exposure for a set of layers, from thumbnails of at most 8 of them."""
    import dask.array as da

    pick = layers[:: max(1, math.ceil(len(layers) / 8))]
    (values,) = session.compute(da.stack([_thumbnail(ds, v, li, 128) for v, li in pick]))
    return exposure(values)


def _export_block(store: str, out: str, view: int, lights: list[int], names: list[str], *,
                  channels: tuple[str, ...], fmt: str, half: bool, scale: float) -> None:
    import zarr

    array = zarr.open_array(store, path=RADIANCE, mode="r")
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
        with (tmp / "manifest.csv").open("w", newline="") as f:
            out = csv.writer(f)
            out.writerow(["file", "theta_light", "phi_light", "theta_view", "phi_view"])
            out.writerows([r[0], *(repr(float(a)) for a in r[1:])] for r in rows)
        session.log(f"export: {len(rows)} layers as {params.format.upper()} -> "
                    f"{params.out_dir}")
        session.compute(*writes)
    return Path(params.out_dir)


def preview(params: PreviewParams, session: Session) -> Path:
    """Draw a contact sheet of a spread of layers with their directions as labels."""
    import dask.array as da
    from matplotlib.figure import Figure

    ds = open_radiance(params.store)
    d = Directions.of(ds)
    layers = spread_pairs(d.theta_view, d.phi_view, d.theta_light, d.phi_light, params.count)
    thumbs = da.stack([_thumbnail(ds, v, li, params.size) for v, li in layers])
    session.log(f"preview: {len(layers)} layers of {params.store} -> {params.out}")
    (images,) = session.compute(thumbs)
    scale = params.exposure or exposure(images)
    cols = min(len(layers), 4 if len(layers) <= 8 else 6)
    rows = math.ceil(len(layers) / cols)
    fig = Figure(figsize=(2.6 * cols, 2.9 * rows + 0.6), dpi=100, layout="constrained")
    attrs = dict(ds.attrs)
    title = f"{Path(params.store).name}: {attrs.get('btf_kind', '?')}"
    if "material" in attrs:
        title += f", {attrs['material'].get('name', 'photo')}"
    if "sampling" in attrs:
        title += f", {attrs['sampling']}"
    fig.suptitle(f"{title} (exposure x{scale:.3g})", fontsize=11)
    for k, ((v, li), image) in enumerate(zip(layers, images, strict=True)):
        ax = fig.add_subplot(rows, cols, k + 1)
        shown = tonemap(image, scale=scale)
        ax.imshow(shown[..., 0] if shown.shape[-1] == 1 else shown,
                  cmap="gray" if shown.shape[-1] == 1 else None, vmin=0, vmax=1,
                  interpolation="nearest")
        ax.set_title(f"light θ={d.theta_light[li]:.0f}° φ={d.phi_light[li]:.0f}°\n"
                     f"view θ={d.theta_view[v]:.0f}° φ={d.phi_view[v]:.0f}°", fontsize=8)
        ax.set_axis_off()
    with atomic_output(params.out, directory=False, overwrite=params.overwrite) as tmp:
        fig.savefig(tmp, format="png")
    return Path(params.out)
