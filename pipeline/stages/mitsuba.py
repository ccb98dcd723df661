"""``btf mitsuba``: render a compressed store with Mitsuba 3 (the ``btf`` BSDF).

Built-in scenes: ``plane`` (the store's square under a directional light of unit irradiance,
seen by an orthographic camera from ``--view``: from straight above it shows the stored layers,
blended between measured directions as ``btf view`` blends them) and ``sphere`` (a unit sphere
seen by a perspective camera, the texture repeated ``--repeat`` times round it). Or any scene
file that names the plugin (``<bsdf type="btf"><string name="store" value="..."/></bsdf>``).
The BSDF is :mod:`tasks.btf_bsdf`; the variant, the plugin's registration and the LLVM check
are :mod:`pipeline.mitsuba_plugin` (docs/mitsuba.md).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.images import write_exr, write_png
from pipeline.params import ParamError, option
from pipeline.session import Session
from pipeline.stage import Stage
from tasks.sampling import direction_vectors
from tasks.tonemap import exposure, to_uint8, tonemap

SCENES = ("plane", "sphere")
VARIANTS = ("auto", "scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb")
SCALAR_SIZE = 64  # pixels a side on the scalar variant unless --size says otherwise


def _angles(text: str, name: str) -> tuple[float, float]:
    try:
        theta, phi = (float(v) for v in text.split(","))
    except ValueError:
        raise ParamError(name, f"expected THETA,PHI in degrees, got {text!r}") from None
    if not 0 <= theta < 90:
        raise ParamError(name, f"theta must be in [0, 90) degrees, got {theta:g}")
    return theta, phi


@dataclasses.dataclass(frozen=True)
class MitsubaParams:
    """Parameters of ``btf mitsuba``."""

    store: str = option(help="compressed store (btf compress, btf ingest FILE.btf) or "
                             "compressed tile set (btf quilt, btf roller on one)",
                        positional=True, path="in", metavar="STORE")
    out: str = option(help="output image: .exr (linear) or .png (tone-mapped)",
                      positional=True, path="out")
    scene: str = option("plane", choices=SCENES,
                        help="built-in scene: plane (orthographic, reproduces the stored "
                             "layers from straight above) or sphere")
    scene_file: str | None = option(None, path="in", metavar="FILE.xml",
                                    help="render this Mitsuba scene file instead (it names "
                                         "the plugin: <bsdf type=\"btf\">; STORE is unused)")
    light: str = option("30,0", metavar="THETA,PHI",
                        help="direction towards the light, degrees (directional, irradiance 1)")
    view: str = option("0,0", metavar="THETA,PHI",
                       help="direction towards the camera, degrees (plane scene)")
    spp: int = option(16, metavar="N", help="samples per pixel")
    size: int | None = option(None, metavar="N",
                              help="image side in pixels (default: the store's texels for "
                                   "the plane, at most 1024; 256 for the sphere; "
                                   f"{SCALAR_SIZE} on the scalar variant)")
    rank: int | None = option(None, metavar="R", help="components used (default: all)")
    level: int = option(0, metavar="N", help="level of detail: eigentextures averaged over "
                                             "blocks of 2^N texels, as btf view --level")
    repeat: float = option(4.0, metavar="X", help="sphere: texture repeats round it")
    surface: tuple[int, ...] | None = option(
        None, metavar="H,W", help="a tile set: texels of its surface on the shape, laid as btf "
                                  "render lays them (default: the sample's size)")
    origin: tuple[int, ...] = option((0, 0), metavar="Y,X",
                                     help="a tile set: first texel of that surface region")
    variant: str = option("auto", choices=VARIANTS,
                          help="Mitsuba variant: auto takes llvm_ad_rgb where LLVM 16+ is "
                               "found, else scalar_rgb (slow)")
    seed: int = option(0, metavar="S", help="seed of the sampler")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        if Path(self.out).suffix.lower() not in (".exr", ".png"):
            raise ParamError("out", f"must end in .exr or .png, got {self.out!r}")
        _angles(self.light, "light")
        _angles(self.view, "view")
        if self.spp < 1:
            raise ParamError("spp", f"must be at least 1, got {self.spp}")
        if self.size is not None and not 8 <= self.size <= 8192:
            raise ParamError("size", f"must be between 8 and 8192, got {self.size}")
        if self.rank is not None and self.rank < 1:
            raise ParamError("rank", f"must be at least 1, got {self.rank}")
        if self.level < 0:
            raise ParamError("level", f"must be at least 0, got {self.level}")
        if self.surface is not None and (len(self.surface) != 2 or min(self.surface) < 1):
            raise ParamError("surface", f"expected H,W (positive), got {self.surface}")
        if len(self.origin) != 2:
            raise ParamError("origin", f"expected Y,X, got {self.origin}")


def scene_dict(params: MitsubaParams, mi, bsdf, texels: int) -> dict:
    """The built-in scene of ``params`` around ``bsdf`` (a ``mi.load_dict`` dictionary)."""
    light = direction_vectors(*_angles(params.light, "light")).tolist()
    emitter = {"type": "directional", "direction": [-c for c in light],
               "irradiance": {"type": "rgb", "value": 1.0}}
    if params.scene == "plane":
        size = params.size or min(texels, 1024)
        eye = (2 * direction_vectors(*_angles(params.view, "view"))).tolist()
        sensor = {"type": "orthographic",  # theta < 90: the eye is never along +y
                  "to_world": mi.ScalarTransform4f().look_at(origin=eye, target=[0, 0, 0],
                                                             up=[0, 1, 0]),
                  "sampler": {"type": "independent", "sample_count": params.spp,
                              "seed": params.seed},
                  "film": {"type": "hdrfilm", "width": size, "height": size,
                           "rfilter": {"type": "box"}}}
        shape = {"type": "rectangle", "bsdf": bsdf}
    else:
        size = params.size or 256
        sensor = {"type": "perspective", "fov": 32,
                  "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4.2],
                                                             target=[0, 0, 0], up=[0, 1, 0]),
                  "sampler": {"type": "independent", "sample_count": params.spp,
                              "seed": params.seed},
                  "film": {"type": "hdrfilm", "width": size, "height": size}}
        # poles up and down (Mitsuba's sphere has them on z, where the camera looks)
        shape = {"type": "sphere", "bsdf": bsdf,
                 "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90)}
    return {"type": "scene", "integrator": {"type": "direct"}, "sensor": sensor,
            "light": emitter, "shape": shape}


def mitsuba(params: MitsubaParams, session: Session) -> Path:
    """Render the scene of ``params``; returns the image's path."""
    from pipeline import mitsuba_plugin

    chosen = mitsuba_plugin.variant(params.variant, log=session.log)
    mi, _ = mitsuba_plugin.import_mitsuba()
    if chosen.startswith("scalar") and params.size is None:  # one sample at a time in Python
        params = dataclasses.replace(params, size=SCALAR_SIZE)
        session.log(f"mitsuba: {chosen}: a small render, {SCALAR_SIZE} x {SCALAR_SIZE} pixels "
                    "(--size for another)")
    if params.scene_file is not None:
        mitsuba_plugin.register()
        scene = mi.load_file(params.scene_file)
        what = params.scene_file
    else:
        surface = {"size": params.surface, "origin": params.origin, "level": params.level}
        bsdf = mitsuba_plugin.bsdf(params.store, params.rank,
                                   uv_scale=params.repeat if params.scene == "sphere" else 1.0,
                                   **surface)
        texels = int(bsdf.tables.v.shape[0])
        scene = mi.load_dict(scene_dict(params, mi, bsdf, texels))
        what = f"{params.scene} of {params.store} ({bsdf.to_string()})"
    session.log(f"mitsuba: {what}, {params.spp} spp, {chosen}")
    start = time.perf_counter()
    image = np.asarray(mi.render(scene, spp=params.spp, seed=params.seed), np.float32)
    seconds = time.perf_counter() - start
    session.log(f"mitsuba: {image.shape[1]} x {image.shape[0]} pixels in {seconds:.2f} s -> "
                f"{params.out}")
    made = (f"Mitsuba {mi.__version__} ({chosen}), the btf BSDF: {what}; {image.shape[1]} x "
            f"{image.shape[0]} pixels, {params.spp} spp, {seconds:.2f} s")
    with atomic_output(params.out, directory=False, overwrite=params.overwrite) as tmp:
        if Path(params.out).suffix.lower() == ".exr":
            write_exr(tmp, image[..., :3], ("R", "G", "B"))
        else:
            write_png(tmp, to_uint8(tonemap(image[..., :3], scale=exposure(image[..., :3]))),
                      text={"btf": made})
    return Path(params.out)


STAGE = Stage("mitsuba", MitsubaParams, mitsuba,
              "render a compressed store with Mitsuba 3 (the btf BSDF)",
              "Render a compressed store with Mitsuba 3 through btf's BSDF plugin (Dr.Jit: "
              "compiled into the llvm variant's kernels): a built-in plane (orthographic; from "
              "straight above it reproduces the stored layers, and between measured "
              "directions shows btf view's blend) or sphere under a directional light of unit "
              "irradiance, or any scene file naming <bsdf type=\"btf\">. Needs Mitsuba 3 "
              "(pip install 'btf-pipeline[mitsuba]') and, for the llvm variant, LLVM 16 or "
              "later (docs/mitsuba.md).")
