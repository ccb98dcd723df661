"""``btf generate``: a procedural BTF with ground truth, rendered tile-parallel into a store.

The graph has two kinds of task. For every spatial shard, one task computes the material fields
of the shard plus a halo wide enough for every shadow and parallax ray (procedural fields are
defined everywhere, so the halo holds true values; a photo is mirrored at its borders). For every
(view, block of lights, shard), one task renders the layers from those fields
(:func:`tasks.shading.render_block`) and writes them to that shard of the store. No task holds
more than one shard of fields and one shard of radiance, and because every texel is computed
from the same numbers however the work is split, the store is bit-identical on every scheduler.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.params import ParamError, option
from pipeline.provenance import provenance
from pipeline.runtime import Session
from pipeline.store import (
    RADIANCE,
    Directions,
    Layout,
    aligned_chunks,
    create_radiance_store,
    store_aligned,
)
from tasks.materials import MATERIALS, Fields, Material, image_fields
from tasks.sampling import SAMPLING_HELP, parse_sampling
from tasks.shading import ShadingModel, render_block

CHANNELS = ("R", "G", "B")
IMAGE_SCALE = 20.0  # default "scale" of a photo material: its relief is 0.2 of it (4 px)


@dataclasses.dataclass(frozen=True)
class GenerateParams:
    """Parameters of ``btf generate``."""

    out: str = option(help="output radiance store (a .zarr directory)", positional=True,
                      path="out")
    material: str | None = option(
        None, choices=tuple(MATERIALS),
        help="procedural material: " + "; ".join(f"{k} ({v.description})"
                                                 for k, v in MATERIALS.items()),
    )
    size: int | None = option(None, help="texels per side (with --albedo: crop the photo)")
    sampling: str = option("abtf:24,8", metavar="NAME", help=f"direction sampling: {SAMPLING_HELP}")
    seed: int = option(0, metavar="S",
                       help="seed of the material; the same seed gives the same store")
    scale: float | None = option(
        None, help="characteristic length of the structure in texels (the exact period for "
                   "tiles); default: the material's own")
    albedo: str | None = option(
        None, path="in", metavar="IMAGE",
        help="EXR or PNG photo to use as albedo and height source instead of a procedural "
             "material (PNG is decoded from sRGB)")
    chunk: int = option(128, help="texels per side of a stored chunk")
    dir_chunk: int = option(16, help="light directions per stored chunk")
    shard: int = option(0, help="texels per side of a shard file grouping several chunks (a "
                                "multiple of --chunk); 0: one file per chunk")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        if self.albedo is None and self.material is None:
            raise ParamError("material", "is required (or give --albedo IMAGE)")
        if self.albedo is not None and self.material is not None:
            raise ParamError("material", "cannot be combined with --albedo")
        if self.size is None and self.albedo is None:
            raise ParamError("size", "is required (unless --albedo gives the size)")
        if self.size is not None and not 8 <= self.size <= 1 << 20:
            raise ParamError("size", f"must be between 8 and 1048576 texels, got {self.size}")
        if self.seed < 0:
            raise ParamError("seed", f"must be non-negative, got {self.seed}")
        try:
            parse_sampling(self.sampling)
        except ValueError as exc:
            raise ParamError("sampling", str(exc)) from None
        if self.scale is not None and not self.scale >= 2:
            raise ParamError("scale", f"must be at least 2 texels, got {self.scale}")
        try:
            self.layout()
        except ValueError as exc:
            raise ParamError("chunk", str(exc)) from None

    def layout(self) -> Layout:
        """The store layout these parameters ask for."""
        return Layout(chunk=self.chunk, dir_chunk=self.dir_chunk, shard=self.shard)


def _blocks(chunks: tuple[int, ...]) -> list[tuple[int, int]]:
    starts = np.concatenate([[0], np.cumsum(chunks)[:-1]]).astype(int)
    return [(int(s), int(c)) for s, c in zip(starts, chunks, strict=True)]


def _material_window(block_info=None, *, material: Material, halo: int, ych, xch):
    i, j = block_info[None]["chunk-location"][:2]
    (y0, ny), (x0, nx) = _blocks(ych)[i], _blocks(xch)[j]
    return material.fields(y0 - halo, x0 - halo, ny + 2 * halo, nx + 2 * halo).pack()


def _slice_window(padded: np.ndarray, y0: int, x0: int, ny: int, nx: int) -> np.ndarray:
    return padded[y0 : y0 + ny, x0 : x0 + nx]


def _crop(window: np.ndarray, halo: int) -> np.ndarray:
    return window[halo : window.shape[0] - halo, halo : window.shape[1] - halo]


def _render(window, views, lights, *, halo: int, model: ShadingModel) -> np.ndarray:
    return render_block(Fields.unpack(window), halo=halo, theta_view=views[:, 0],
                        phi_view=views[:, 1], theta_light=lights[:, 0], phi_light=lights[:, 1],
                        model=model)


def field_windows(source: Material | Fields, ych, xch, halo: int):
    """Dask array whose blocks are the packed fields of each spatial block plus its halo."""
    import dask
    import dask.array as da

    wy, wx = tuple(c + 2 * halo for c in ych), tuple(c + 2 * halo for c in xch)
    if isinstance(source, Material):
        return da.map_blocks(_material_window, chunks=(wy, wx, (6,)), dtype=np.float32,
                             meta=np.empty((0, 0, 0), np.float32), material=source, halo=halo,
                             ych=ych, xch=xch)
    padded = dask.delayed(np.pad(source.pack(), ((halo, halo), (halo, halo), (0, 0)),
                                 mode="reflect"), pure=True)
    return da.block([
        [da.from_delayed(dask.delayed(_slice_window)(padded, y0, x0, ny + 2 * halo, nx + 2 * halo),
                         shape=(ny + 2 * halo, nx + 2 * halo, 6), dtype=np.float32)
         for x0, nx in _blocks(xch)]
        for y0, ny in _blocks(ych)
    ])


def _photo(params: GenerateParams) -> tuple[Fields, dict]:
    from pipeline.images import read_image

    path = Path(params.albedo)
    if not path.is_file():
        raise BTFError(f"{path}: albedo image not found")
    pixels, _ = read_image(path, srgb=path.suffix.lower() == ".png")
    if not np.all(np.isfinite(pixels)):
        raise BTFError(f"{path}: the albedo image has non-finite pixels")
    if params.size is not None:
        h, w = pixels.shape[:2]
        if params.size > min(h, w):
            raise BTFError(f"{path}: --size {params.size} is larger than the image ({h}x{w})")
        y0, x0 = (h - params.size) // 2, (w - params.size) // 2
        pixels = pixels[y0 : y0 + params.size, x0 : x0 + params.size]
    relief = 0.2 * (params.scale or IMAGE_SCALE)
    info = {"albedo_image": str(path), "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "relief": relief}
    return image_fields(pixels, relief=relief), info


def generate(params: GenerateParams, session: Session) -> Path:
    """Render the store described by ``params``; returns its path."""
    import dask.array as da

    sampling = parse_sampling(params.sampling)
    if params.albedo is not None:
        source, material_info = _photo(params)
        ny, nx = source.height.shape
    else:
        source = Material(params.material, seed=params.seed, scale=params.scale)
        ny = nx = params.size
        material_info = {"name": source.name, "seed": source.seed,
                         "scale": source.effective_scale, "relief": source.relief}
        if source.name == "tiles":
            material_info["period"] = round(source.effective_scale)
    relief = material_info["relief"]
    model = ShadingModel(relief=relief)
    halo = model.halo(float(sampling.theta_view.max()), float(sampling.theta_light.max()))
    directions = Directions(sampling.theta_view, sampling.phi_view, sampling.theta_light,
                            sampling.phi_light)
    attrs = {
        "btf_kind": directions.kind,
        "source": "generate",
        "sampling": params.sampling,
        "material": material_info,
        "shading": {**dataclasses.asdict(model), "halo": halo},
        "provenance": provenance("generate", params),
    }
    with atomic_output(params.out, overwrite=params.overwrite) as tmp:
        group = create_radiance_store(tmp, directions=directions, ny=ny, nx=nx,
                                      channels=CHANNELS, layout=params.layout(), attrs=attrs,
                                      truth=True)
        vch, lch, ych, xch, _ = aligned_chunks(group[RADIANCE])
        windows = field_windows(source, ych, xch, halo)
        views = da.from_array(np.stack([sampling.theta_view, sampling.phi_view], -1),
                              chunks=(vch, 2))
        lights = da.from_array(np.stack([sampling.theta_light, sampling.phi_light], -1),
                               chunks=(lch, 2))
        radiance = da.blockwise(
            _render, "vlyxc", windows, "yxf", views, "vd", lights, "ld",
            new_axes={"c": len(CHANNELS)}, adjust_chunks={"y": ych, "x": xch},
            concatenate=True, align_arrays=False, dtype=np.float32,
            meta=np.empty((0,) * 5, np.float32), halo=halo,
            model=model,
        )
        truth = windows.map_blocks(_crop, chunks=(ych, xch, (6,)), dtype=np.float32, halo=halo)
        write = store_aligned(
            [radiance, truth[..., 0], truth[..., 1:4], truth[..., 4], truth[..., 5]],
            [group[name] for name in (RADIANCE, "height", "albedo", "roughness", "specular")],
        )
        session.log(f"generate: {len(sampling.theta_view)} x {len(sampling.theta_light)} "
                    f"layers of {ny} x {nx} texels -> {params.out}")
        session.compute(write)
    return Path(params.out)
