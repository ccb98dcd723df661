"""Rendering BTF layers of a height-field material with Mitsuba 3's path tracer.

The same layers as :mod:`tasks.shading` describes, but light transport from a physically based
renderer: the material's height field is a triangle mesh (one vertex per texel centre, in the
store's frame: +x along columns, +y towards row 0, z the height), its fields drive a Mitsuba
BSDF per vertex (albedo, GGX roughness, F0; interpolated over each triangle), one directional
emitter per light direction and Mitsuba's ``path`` integrator give masking, cast shadows and
interreflections.

- **Camera.** Each texel's samples are rays of the view direction through points spread
  uniformly over the texel's square on the reference plane ``z = relief / 2`` (rectified onto
  the sample plane as measured BTFs are, and as :mod:`tasks.shading` registers its views): an
  orthographic camera whose pixels are the texels, box-filtered. The mean of ``spp`` such
  samples is the texel's value.
- **Radiometry.** The light has irradiance pi (measured perpendicular to its direction), as in
  :mod:`tasks.shading`: a white Lambertian texel facing the light has radiance 1.
- **Edges.** The mesh covers the block plus ``halo`` texels of the material's own surface on
  every side, so parallax, shadows and interreflections at the kept block's border come from
  true neighbours; rays leaving the mesh see black.
- **Noise and seeds.** Samples are drawn by Mitsuba's ``multijitter`` sampler (the texel's
  footprint and every other dimension stratified per texel: 2-4x less noise than independent
  samples at 16 spp), seeded from the render's seed, the layer's (view, light) indices and
  the block's first texel (:func:`sample_seed`): every texel is drawn the same way whatever
  the scheduler, so a store is bit-identical on every scheduler.

BSDFs (:data:`BSDFS`): ``principled`` (Disney/Burley's, the material's albedo as base colour,
``roughness = sqrt(alpha)``; Mitsuba takes one ``specular``: the field's median F0 / 0.08),
``conductor`` (a rough conductor whose reflectance is the albedo, GGX ``alpha`` from the
field), ``plastic`` (a rough dielectric interface over the albedo: Mitsuba's
``roughplastic``, the field's median ``alpha``) and ``diffuse``. Mitsuba is imported when a
render starts, not with this module.
"""

from __future__ import annotations

import hashlib
import math
import threading
from dataclasses import dataclass

import numpy as np

from tasks.materials import Fields
from tasks.sampling import direction_vectors

BSDFS = ("principled", "conductor", "plastic", "diffuse")
SAMPLER = "multijitter"  # stratified per texel: 2-4x less noise than independent at 16 spp
BATCH_SAMPLES = 1 << 21  # samples traced at once: bounds the renderer's memory (~0.5 GB)
_LOCK = threading.Lock()  # Mitsuba's variant and Dr.Jit's state are per process


@dataclass(frozen=True)
class PathTracer:
    """Parameters of the path-traced renderer.

    ``spp`` samples per texel; ``max_depth`` Mitsuba's path length (2: direct light only; 4:
    up to two interreflections); ``variant`` the Mitsuba variant (``llvm_ad_rgb``,
    ``scalar_rgb``, ``cuda_ad_rgb``).
    """

    relief: float
    bsdf: str = "principled"
    spp: int = 64
    max_depth: int = 4
    seed: int = 0
    variant: str = "llvm_ad_rgb"

    def __post_init__(self):
        if self.bsdf not in BSDFS:
            raise ValueError(f"bsdf must be one of {', '.join(BSDFS)}, got {self.bsdf!r}")
        if not self.relief > 0:
            raise ValueError(f"relief must be positive, got {self.relief}")
        if self.spp < 1 or self.max_depth < 2:
            raise ValueError("spp must be at least 1 and max_depth at least 2")
        if stratified_spp(self.spp) != self.spp:
            raise ValueError(f"spp {self.spp} is not a stratified count: the nearest is "
                             f"{stratified_spp(self.spp)}")

    @property
    def reference(self) -> float:
        """Height of the plane the views are registered on: half the relief."""
        return 0.5 * self.relief


def stratified_spp(spp: int) -> int:
    """The spp Mitsuba's multijitter sampler takes for ``spp``: an ``a x b`` grid of strata.

    ``a = ceil(sqrt(spp))``, ``b = ceil(spp / a)``: squares (4, 16, 64, 256) and products of
    near factors (12, 20) stay as they are, other counts round up.
    """
    a = math.ceil(math.sqrt(spp))
    return a * math.ceil(spp / a)


def sample_seed(seed: int, view: int, light: int, y0: int, x0: int) -> int:
    """The sampler's seed of one layer of one block (32 bits, from all five numbers)."""
    digest = hashlib.blake2b(np.array([seed, view, light, y0, x0], np.int64).tobytes(),
                             digest_size=4).digest()
    return int.from_bytes(digest, "little")


def _bsdf(mi, kind: str, fields: Fields) -> dict:
    attribute = {"type": "mesh_attribute"}
    if kind == "principled":
        return {"type": "principled", "base_color": {**attribute, "name": "vertex_albedo"},
                "roughness": {**attribute, "name": "vertex_roughness"},
                "specular": float(np.clip(np.median(fields.specular) / 0.08, 0.0, 1.0))}
    if kind == "conductor":
        return {"type": "roughconductor", "material": "none", "distribution": "ggx",
                "specular_reflectance": {**attribute, "name": "vertex_albedo"},
                "alpha": {**attribute, "name": "vertex_alpha"}}
    if kind == "plastic":
        return {"type": "roughplastic", "distribution": "ggx",
                "alpha": float(np.clip(np.median(fields.roughness), 1e-3, 1.0)),
                # roughplastic needs the reflectance's mean: a bitmap over the mesh's uv
                "diffuse_reflectance": {"type": "bitmap", "raw": True, "filter_type": "bilinear",
                                        "wrap_mode": "clamp", "bitmap": mi.Bitmap(np.clip(
                                            fields.albedo, 0.0, 1.0).astype(np.float32))}}
    return {"type": "diffuse", "reflectance": {**attribute, "name": "vertex_albedo"}}


def height_mesh(mi, dr, fields: Fields, bsdf: str, *, origin: tuple[int, int] = (0, 0)):
    """A Mitsuba mesh of ``fields``' height field with its BSDF and per-vertex fields.

    Vertex ``(r, c)`` sits at the texel centre ``(x0 + c + 0.5, -(y0 + r + 0.5), height)``;
    each grid square is two triangles facing +z.
    """
    h = np.asarray(fields.height, np.float32)
    ny, nx = h.shape
    y0, x0 = origin
    rows, cols = np.mgrid[0:ny, 0:nx]
    positions = np.stack([x0 + cols + 0.5, -(y0 + rows + 0.5), h], -1).reshape(-1, 3)
    first = (rows[:-1, :-1] * nx + cols[:-1, :-1]).astype(np.uint32).ravel()
    faces = np.concatenate([np.stack([first, first + nx, first + 1], -1),
                            np.stack([first + 1, first + nx, first + nx + 1], -1)])
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_bsdf(mi, bsdf, fields))
    mesh = mi.Mesh("height_field", ny * nx, len(faces), props=props,
                   has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    texcoords = np.stack([(cols + 0.5) / nx, (rows + 0.5) / ny], -1).reshape(-1, 2)
    params["vertex_texcoords"] = dr.ravel(mi.Point2f(*texcoords.astype(np.float32).T))
    params["vertex_positions"] = dr.ravel(mi.Point3f(*positions.astype(np.float32).T))
    params["faces"] = dr.ravel(mi.Vector3u(*faces.T))
    params.update()
    alpha = np.clip(np.asarray(fields.roughness, np.float32), 1e-3, 1.0)
    per_vertex = {
        "vertex_albedo": np.clip(fields.albedo, 0.0, 1.0).reshape(-1, 3),
        "vertex_alpha": alpha.reshape(-1, 1),
        "vertex_roughness": np.sqrt(alpha).reshape(-1, 1),
    }
    for name, values in per_vertex.items():
        mesh.add_attribute(name, values.shape[1], mi.Float(values.astype(np.float32).ravel()))
    return mesh


def render_block(
    fields: Fields, *, halo: int, theta_view: np.ndarray, phi_view: np.ndarray,
    theta_light: np.ndarray, phi_light: np.ndarray, view_index: np.ndarray,
    light_index: np.ndarray, origin: tuple[int, int], tracer: PathTracer,
) -> np.ndarray:
    """Path-traced radiance ``(views, lights, ny, nx, 3)`` float32 of a block without its halo.

    ``fields`` cover the block plus ``halo`` texels on every side; ``origin`` is the block's
    first texel in the store and ``view_index``/``light_index`` the layers' indices there (the
    samples' seeds come from them, :func:`sample_seed`).
    """
    with _LOCK:
        import drjit as dr
        import mitsuba as mi

        if mi.variant() != tracer.variant:
            mi.set_variant(tracer.variant)
        return _render(mi, dr, fields, halo, theta_view, phi_view, theta_light, phi_light,
                       view_index, light_index, origin, tracer)


def _render(mi, dr, fields, halo, theta_view, phi_view, theta_light, phi_light, view_index,
            light_index, origin, tracer):
    ny, nx = fields.height.shape[0] - 2 * halo, fields.height.shape[1] - 2 * halo
    y0, x0 = origin
    mesh = height_mesh(mi, dr, fields, tracer.bsdf, origin=(y0 - halo, x0 - halo))
    scene = mi.load_dict({"type": "scene", "surface": mesh,
                          "sun": {"type": "directional", "direction": [0.0, 0.0, -1.0],
                                  "irradiance": {"type": "rgb", "value": math.pi}}})
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.startswith("sun.") and k.endswith("to_world"))
    integrator = mi.load_dict({"type": "path", "max_depth": tracer.max_depth,
                               "hide_emitters": True})
    sampler = mi.load_dict({"type": SAMPLER, "sample_count": tracer.spp})
    sampler.set_samples_per_wavefront(tracer.spp)  # lanes: a texel's spp samples in a row
    spp = tracer.spp
    rows = max(1, min(ny, BATCH_SAMPLES // (nx * spp)))
    views = direction_vectors(theta_view, phi_view)
    lights = direction_vectors(theta_light, phi_light)
    out = np.empty((len(views), len(lights), ny, nx, 3), np.float32)
    top = tracer.relief - tracer.reference + 1.0  # above the whole relief
    for il, light in enumerate(lights):
        params[key] = mi.Transform4f().look_at(origin=[0, 0, 0],
                                               target=[float(-c) for c in light],
                                               up=_up(-light))
        params.update()
        for iv, view in enumerate(views):
            d = mi.Vector3f(*(float(c) for c in view))
            lift = top / max(float(view[2]), 1e-3)
            for r0 in range(0, ny, rows):
                n_rows = min(rows, ny - r0)
                count = n_rows * nx * spp
                sampler.seed(sample_seed(tracer.seed, int(view_index[iv]),
                                         int(light_index[il]), y0 + r0, x0), count)
                texel = dr.arange(mi.UInt32, count) // spp
                row = mi.Float(texel // nx + (y0 + r0))
                col = mi.Float(texel % nx + x0)
                jitter = sampler.next_2d()
                on_plane = mi.Point3f(col + jitter.x, -(row + jitter.y), tracer.reference)
                ray = mi.Ray3f(on_plane + d * lift, -d)
                value, _, _ = integrator.sample(scene, sampler, ray)
                samples = np.asarray(value, np.float32).reshape(3, n_rows, nx, spp)
                out[iv, il, r0 : r0 + n_rows] = samples.mean(axis=-1, dtype=np.float64
                                                            ).transpose(1, 2, 0)
    return out


def _up(direction: np.ndarray) -> list[float]:
    """A unit vector not parallel to ``direction`` (look_at's up)."""
    return [1.0, 0.0, 0.0] if abs(float(direction[2])) > 0.9 else [0.0, 0.0, 1.0]
