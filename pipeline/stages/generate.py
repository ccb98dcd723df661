"""``btf generate``: a procedural BTF with ground truth, rendered tile-parallel into a store.

The graph has two kinds of task. For every spatial task block (whole chunks, about 512 texels a
side, :func:`pipeline.graphs.blocks.task_block`), one task computes the material fields of the block
plus a halo wide enough for every shadow and parallax ray. Procedural fields are defined
everywhere, so the halo holds true values; a photo's fields are computed once, written to the
store's ground-truth arrays, and read back by each block with the photo mirrored at its
borders. For every (view, block of lights, spatial block), one task renders the layers from
those fields (:func:`tasks.shading.render_block`) and writes them. No task holds more than one
block of fields and one block of radiance, and because every texel is computed from the same
numbers however the work is split, the store is bit-identical on every scheduler.
"""

from __future__ import annotations

import dataclasses
import math
import uuid
from collections.abc import Hashable
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.blockwise import blockwise
from pipeline.errors import BTFError
from pipeline.graphs.blocks import aligned_chunks, store_aligned, task_side
from pipeline.params import ParamError, check_seed, option
from pipeline.planning import Shape, StageEstimate, rate
from pipeline.provenance import provenance
from pipeline.resume import Progress
from pipeline.session import Session
from pipeline.stage import Stage
from pipeline.stores.base import RADIANCE, Directions, location, readable
from pipeline.stores.radiance import TRUTH_DIMS, LayoutOptions, create_radiance_store
from tasks.materials import (
    HEIGHTS,
    MATERIALS,
    PHOTO_SCALE,
    Fields,
    Material,
    bump_height,
    bump_relief,
    image_fields,
    photo_relief,
)
from tasks.pathtrace import BSDFS, PathTracer, stratified_spp
from tasks.pathtrace import render_block as trace_block
from tasks.sampling import SAMPLING_HELP, parse_sampling
from tasks.shading import SHADOWS, VIEWS, ShadingModel, render_block

CHANNELS = ("R", "G", "B")
RENDERERS = ("shading", "mitsuba")
DEFAULT_SPP = 64
DEFAULT_BOUNCES = 2
PATH_MARGIN = 8  # texels of surface beyond the shading model's halo, for interreflections


@dataclasses.dataclass(frozen=True)
class GenerateParams(LayoutOptions):
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
    height: str | None = option(
        None, choices=HEIGHTS,
        help="with --albedo, where the relief comes from: photo (the photo's band-passed "
             "lightness, dark detail low; the default) or bumps (smooth bumps of two scales, "
             "--scale and a third of it, drawn from --seed and independent of the photo)")
    renderer: str = option(
        "shading", choices=RENDERERS,
        help="shading: btf's own model (height-field parallax, cast shadows, diffuse + GGX, an "
             "ambient term; fast, exact ground truth); mitsuba: Mitsuba 3's path tracer on the "
             "height field as a mesh (masking, shadows, interreflections; needs the [mitsuba] "
             "extra and LLVM 16+)")
    bsdf: str | None = option(
        None, choices=BSDFS,
        help="--renderer mitsuba: the surface's BSDF, driven by the material's fields "
             "(default principled; conductor: a rough conductor reflecting the albedo; "
             "plastic: a rough dielectric over the albedo)")
    spp: int | None = option(None, metavar="N",
                             help="--renderer mitsuba: samples per texel, stratified (default "
                                  f"{DEFAULT_SPP}: relative noise about 1%% in the median layer, "
                                  "2%% in the worst; 256 for under 1%% everywhere)")
    bounces: int | None = option(None, metavar="N",
                                 help="--renderer mitsuba: interreflections followed (default "
                                      f"{DEFAULT_BOUNCES}; 0: direct light only)")
    variant: str | None = option(None, choices=("auto", "llvm_ad_rgb", "cuda_ad_rgb"),
                                 record=False,
                                 help="--renderer mitsuba: Mitsuba variant (default auto: "
                                      "llvm_ad_rgb; cuda_ad_rgb on a GPU)")
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
        check_seed(self.seed)
        if self.height is not None and self.albedo is None:
            raise ParamError("height", "only applies with --albedo")
        if self.albedo is not None and self.height != "bumps" and self.seed != 0:
            raise ParamError("seed", "has no effect with --albedo (a photo has no randomness; "
                                     "--height bumps draws its bumps from it)")
        try:
            parse_sampling(self.sampling)
        except ValueError as exc:
            raise ParamError("sampling", str(exc)) from None
        if self.scale is not None and not self.scale >= 2:
            raise ParamError("scale", f"must be at least 2 texels, got {self.scale}")
        if self.renderer != "mitsuba":
            for name in ("bsdf", "spp", "bounces", "variant"):
                if getattr(self, name) is not None:
                    raise ParamError(name, "only applies with --renderer mitsuba")
        if self.spp is not None and not 1 <= self.spp <= 1 << 16:
            raise ParamError("spp", f"must be between 1 and 65536, got {self.spp}")
        if self.spp is not None and stratified_spp(self.spp) != self.spp:
            raise ParamError("spp", f"{self.spp} samples do not fill a grid of strata: use "
                                    f"{stratified_spp(self.spp)} (squares such as 16, 64, 256 "
                                    "always do)")
        if self.bounces is not None and not 0 <= self.bounces <= 16:
            raise ParamError("bounces", f"must be between 0 and 16, got {self.bounces}")
        self.layout()  # raises ParamError naming the bad option

    def tracer(self, relief: float, variant: str = "llvm_ad_rgb") -> PathTracer:
        """The path tracer of ``--renderer mitsuba`` for a material of ``relief``."""
        return PathTracer(relief=relief, bsdf=self.bsdf or "principled",
                          spp=self.spp or DEFAULT_SPP,
                          max_depth=2 + (DEFAULT_BOUNCES if self.bounces is None
                                         else self.bounces),
                          seed=self.seed, variant=variant)


def _block(chunks: tuple[int, ...], i: int) -> tuple[int, int]:
    """Start and size of block ``i`` of one axis of dask chunks."""
    return int(sum(chunks[:i])), int(chunks[i])


def _material_window(block_info=None, *, material: Material, halo: int, ych, xch):
    i, j = block_info[None]["chunk-location"][:2]
    (y0, ny), (x0, nx) = _block(ych, i), _block(xch, j)
    return material.fields(y0 - halo, x0 - halo, ny + 2 * halo, nx + 2 * halo).pack()


def _stored_window(block_info=None, *, store: str, halo: int, ych, xch):
    """Packed fields of a block plus halo, read from the store's truth arrays.

    The photo is mirrored at its borders: the halo of a border block has no true values.
    """
    i, j = block_info[None]["chunk-location"][:2]
    (y0, ny), (x0, nx) = _block(ych, i), _block(xch, j)
    group = readable(store)
    height, width = group["height"].shape
    ya, yb = max(0, y0 - halo), min(height, y0 + ny + halo)
    xa, xb = max(0, x0 - halo), min(width, x0 + nx + halo)
    region = (slice(ya, yb), slice(xa, xb))
    packed = Fields(group["height"][region], group["albedo"][region],
                    group["roughness"][region], group["specular"][region]).pack()
    pad = ((ya - (y0 - halo), y0 + ny + halo - yb), (xa - (x0 - halo), x0 + nx + halo - xb),
           (0, 0))
    return np.pad(packed, pad, mode="reflect")


def _crop(window: np.ndarray, halo: int) -> np.ndarray:
    return window[halo : window.shape[0] - halo, halo : window.shape[1] - halo]


def _render(window, views, lights, origin, *, halo: int, model: ShadingModel,
            tracer: PathTracer | None, source: Hashable) -> np.ndarray:
    """One block's layers: ``views``/``lights`` rows are (theta, phi, index in the store).

    ``source``: what the fields are (the material, or a photo's store and run): with the
    block's place and size, what its window is (the shading caches' key).
    """
    if tracer is None:
        place = (int(origin[0, 0, 0]), int(origin[0, 0, 1]))
        return render_block(Fields.unpack(window), halo=halo, theta_view=views[:, 0],
                            phi_view=views[:, 1], theta_light=lights[:, 0],
                            phi_light=lights[:, 1], model=model,
                            key=(source, place, window.shape))
    return trace_block(Fields.unpack(window), halo=halo, theta_view=views[:, 0],
                       phi_view=views[:, 1], theta_light=lights[:, 0], phi_light=lights[:, 1],
                       view_index=views[:, 2].astype(int), light_index=lights[:, 2].astype(int),
                       origin=(int(origin[0, 0, 0]), int(origin[0, 0, 1])), tracer=tracer)


def field_windows(source: Material | str, ych, xch, halo: int):
    """Dask array whose blocks are the packed fields of each spatial block plus its halo.

    ``source`` is a procedural material, or the path of a store whose truth arrays hold a
    photo's fields.
    """
    import dask.array as da

    wy, wx = tuple(c + 2 * halo for c in ych), tuple(c + 2 * halo for c in xch)
    window = (partial(_material_window, material=source) if isinstance(source, Material)
              else partial(_stored_window, store=source))
    return da.map_blocks(window, chunks=(wy, wx, (6,)), dtype=np.float32,
                         meta=np.empty((0, 0, 0), np.float32), halo=halo, ych=ych, xch=xch)


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
    info = {"albedo_image": str(path)}
    if params.height == "bumps":
        scale = float(PHOTO_SCALE if params.scale is None else params.scale)
        relief = bump_relief(scale)
        height = bump_height(*pixels.shape[:2], seed=params.seed, scale=scale, relief=relief)
        info.update(height="bumps", seed=params.seed, scale=scale)
    else:
        relief, height = photo_relief(params.scale), None
    info["relief"] = relief
    return image_fields(pixels, relief=relief, height=height), info


def _choose_material(params: GenerateParams
                     ) -> tuple[Fields | None, Material | None, dict, int, int]:
    """The photo or procedural material of ``params``, its attrs record and its size.

    Returns ``(photo, material, material_info, ny, nx)``: exactly one of ``photo`` and
    ``material`` is set.
    """
    if params.albedo is not None:
        photo, material_info = _photo(params)
        ny, nx = photo.height.shape
        return photo, None, material_info, ny, nx
    material = Material(params.material, seed=params.seed, scale=params.scale)
    ny = nx = params.size
    material_info = {"name": material.name, "seed": material.seed,
                     "scale": material.effective_scale, "relief": material.relief}
    if material.name == "tiles":
        material_info["period"] = round(material.effective_scale)
    return None, material, material_info, ny, nx


def _attrs(params: GenerateParams, material_info: dict, model: ShadingModel, halo: int,
           tracer: PathTracer | None) -> dict:
    """The store's attrs: sampling, material, shading and provenance (its kind: the store's)."""
    if tracer is None:
        shading = {**dataclasses.asdict(model), "reference": model.reference, "halo": halo}
    else:
        from importlib.metadata import version

        shading = {"renderer": "mitsuba " + version("mitsuba"), "integrator": "path",
                   **dataclasses.asdict(tracer), "reference": tracer.reference, "halo": halo}
    return {
        "source": "generate",
        "sampling": params.sampling,
        "material": material_info,
        "shading": shading,
        "provenance": provenance("generate", params),
    }


def _write_photo_truth(group, photo: Fields) -> None:
    """Write a photo's fields to the truth arrays (they fit in memory: written once)."""
    for name, values in zip(TRUTH_DIMS, (photo.height, photo.albedo, photo.roughness,
                                         photo.specular), strict=True):
        group[name][...] = values


def _graph(group, tmp, sampling, source: Material | None, *, halo: int,
           model: ShadingModel, tracer: PathTracer | None = None) -> tuple[list, list]:
    """The dask arrays to store and their target arrays: radiance, and a material's truth.

    ``source`` is the procedural material, or ``None`` for a photo, whose fields are read
    back per block from the truth arrays of the store at ``tmp``.
    """
    import dask.array as da

    truth = [group[name] for name in TRUTH_DIMS]
    vch, lch, ych, xch, _ = aligned_chunks(group[RADIANCE])
    where = location(tmp) if source is None else source  # a photo is read back per block
    windows = field_windows(where, ych, xch, halo)
    # what the windows are, for the shading caches: a material's are its own; a photo's are
    # this run's (a cluster's workers keep their caches from run to run)
    identity = source if source is not None else (where, uuid.uuid4().hex)
    views = da.from_array(np.stack([sampling.theta_view, sampling.phi_view,
                                    np.arange(len(sampling.theta_view))], -1), chunks=(vch, 3))
    lights = da.from_array(np.stack([sampling.theta_light, sampling.phi_light,
                                     np.arange(len(sampling.theta_light))], -1),
                           chunks=(lch, 3))
    starts = np.stack(np.meshgrid(np.cumsum((0, *ych[:-1])), np.cumsum((0, *xch[:-1])),
                                  indexing="ij"), -1)
    origins = da.from_array(starts, chunks=(1, 1, 2))  # each block's first texel
    radiance = blockwise(
        _render, "vlyxc", windows, "yxf", views, "vd", lights, "ld", origins, "yxo",
        new_axes={"c": len(CHANNELS)}, adjust_chunks={"y": ych, "x": xch},
        align_arrays=False, dtype=np.float32,
        meta=np.empty((0,) * 5, np.float32), halo=halo, model=model, tracer=tracer,
        source=identity,
    )
    sources, targets = [radiance], [group[RADIANCE]]
    if source is not None:
        fields = windows.map_blocks(_crop, chunks=(ych, xch, (6,)), dtype=np.float32,
                                    halo=halo)
        sources += [fields[..., 0], fields[..., 1:4], fields[..., 4], fields[..., 5]]
        targets += truth
    return sources, targets


def generate(params: GenerateParams, session: Session) -> Path:
    """Render the store described by ``params``; returns its path."""
    sampling = parse_sampling(params.sampling)
    photo, material, material_info, ny, nx = _choose_material(params)
    model = ShadingModel(relief=material_info["relief"])
    halo = model.halo(float(sampling.theta_view.max()), float(sampling.theta_light.max()))
    tracer = None
    if params.renderer == "mitsuba":
        tracer = params.tracer(material_info["relief"], _variant(params, session))
        halo += PATH_MARGIN
    directions = Directions(sampling.theta_view, sampling.phi_view, sampling.theta_light,
                            sampling.phi_light)
    attrs = _attrs(params, material_info, model, halo, tracer)
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"]) as tmp:
        def create():
            made = create_radiance_store(tmp, directions=directions, ny=ny, nx=nx,
                                         channels=CHANNELS, layout=params.layout(),
                                         attrs=attrs, truth=True)
            if photo is not None:
                _write_photo_truth(made, photo)
            return made

        progress = Progress(tmp)
        group = progress.skeleton(create)
        sources, targets = _graph(group, tmp, sampling, material, halo=halo, model=model,
                                  tracer=tracer)
        how = "" if tracer is None else (f", path traced by Mitsuba ({tracer.variant}, "
                                         f"{tracer.bsdf}, {tracer.spp} spp, "
                                         f"{tracer.max_depth - 2} bounces)")
        session.log(f"generate: {len(sampling.theta_view)} x {len(sampling.theta_light)} "
                    f"layers of {ny} x {nx} texels{how} -> {params.out}")
        if progress.count():
            session.log(f"generate: resuming an interrupted run: {progress.count()} blocks "
                        f"already written in {tmp}")
        try:
            session.compute(store_aligned(sources, targets, progress=progress))
        finally:  # the stages after it in this process (btf run, threads) do not keep them
            SHADOWS.clear()
            VIEWS.clear()
    return Path(params.out)


def _variant(params: GenerateParams, session: Session) -> str:
    """The Mitsuba variant the path tracer runs on: a vectorised one, or an error."""
    from pipeline.mitsuba_plugin import variant

    chosen = variant(params.variant or "auto", log=lambda _: None)
    if chosen.startswith("scalar"):
        raise BTFError("--renderer mitsuba needs Mitsuba's llvm variant (LLVM 16 or later; on "
                       "Debian 12: apt-get install libllvm19) or a GPU (--variant "
                       "cuda_ad_rgb): the scalar variant would trace one sample at a time")
    return chosen


def _estimate(params, shapes: dict) -> tuple[StageEstimate, Shape]:
    if params.albedo is not None:
        return None  # the size comes from the photo
    s = parse_sampling(params.sampling)
    nv, nl, n = s.theta_view.size, s.theta_light.size, params.size**2
    nc = 3
    layout = params.layout()
    side = min(task_side(layout.shard or layout.chunk), params.size)
    spatial = math.ceil(params.size / side) ** 2
    light_blocks = math.ceil(nl / layout.dir_chunk)
    block = side * side * min(layout.dir_chunk, nl) * nc * 4
    per_core, source = rate("generate_texel_directions_per_core_second")
    if params.renderer == "mitsuba":  # a rate of path samples: one texel direction is spp
        per_core, source = rate("generate_path_samples_per_core_second")
        per_core /= params.spp or DEFAULT_SPP
    plan = StageEstimate("generate", "", bytes_written=nv * nl * n * nc * layout.itemsize
                         + n * 6 * 4,
                         tasks=nv * light_blocks * spatial + spatial, passes=1, input_reads=0,
                         task_bytes=4 * block + (side + 64) ** 2 * 6 * 4,
                         # the shadow and view caches of each process (the path tracer
                         # keeps none)
                         process_bytes=0 if params.renderer == "mitsuba"
                         else SHADOWS.limit + VIEWS.limit,
                         client_bytes=0, core_seconds=nv * nl * n / per_core, rate_source=source,
                         option="--chunk / --dir-chunk (smaller task blocks)")
    return plan, Shape("btf", (nv, nl, params.size, params.size, nc), layout.chunk,
                       layout.dir_chunk, unit=layout.shard or layout.chunk, truth=True,
                       itemsize=layout.itemsize)



def _directions(params: GenerateParams, source) -> Directions:
    """The directions of the store ``generate`` makes: its sampling's."""
    s = parse_sampling(params.sampling)
    return Directions(s.theta_view, s.phi_view, s.theta_light, s.phi_light)

STAGE = Stage("generate", GenerateParams, generate,
              "render a procedural BTF with ground truth into a store",
              "Render a procedural material (or a photo with --albedo) under a direction "
              "sampling, tile by tile, straight into a radiance store. The store also holds "
              "the ground-truth height, albedo, roughness and specular fields. The same "
              "arguments give a bit-identical store on every scheduler.", makes_store=True,
              estimate=_estimate, whole="a measurement: the stages after it read all of it",
              directions=_directions)
