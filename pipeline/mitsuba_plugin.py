"""Mitsuba 3 renders btf's stores: the ``btf`` BSDF plugin, its variant, built-in scenes.

:func:`register` makes ``<bsdf type="btf"><string name="store" value="STORE"/></bsdf>``
usable in any scene file and in ``mi.load_dict`` (``{"type": "btf", "store": STORE}``) in this
process; the BSDF itself is :mod:`tasks.btf_bsdf` (Dr.Jit), fed by :func:`tables` from a
compressed store. :func:`variant` picks the variant: ``llvm_ad_rgb`` where the system's LLVM
can run Mitsuba's kernels (LLVM 16 or later; found in a subprocess, because an older one
aborts the process at the first kernel), else ``scalar_rgb`` with a message.

Optional: ``pip install 'btf-pipeline[mitsuba]'`` (and, for the llvm variants, a libLLVM of
version 16 or later; on Debian 12 ``apt-get install libllvm19``).
"""

from __future__ import annotations

import glob
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from pipeline.errors import BTFError

LLVM_GLOBS = ("/usr/lib/x86_64-linux-gnu/libLLVM.so.[12][0-9]*", "/usr/lib/*/libLLVM.so.[12][0-9]*",
              "/usr/lib/llvm-*/lib/libLLVM.so.[12][0-9]*")
_PROBE = ("import mitsuba as mi, drjit as dr; mi.set_variant('llvm_ad_rgb'); "
          "x = dr.minimum(mi.Float([1.0, 2.0]), mi.Float([2.0, 1.0])); dr.eval(x); "
          "print(float(dr.sum(x)[0]) if hasattr(dr.sum(x), '__getitem__') else float(dr.sum(x)))")


def import_mitsuba():
    """``(mitsuba, drjit)``, or :class:`BTFError` saying how to install them."""
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError:
        raise BTFError("Mitsuba 3 is not installed: pip install 'btf-pipeline[mitsuba]' "
                       "(or pip install mitsuba)") from None
    return mi, dr


def llvm_library() -> str | None:
    """A libLLVM of version 16 or later on this system (None: none found).

    ``DRJIT_LIBLLVM_PATH`` if set, else the newest of the usual places.
    """
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return os.environ["DRJIT_LIBLLVM_PATH"]
    found = []
    for pattern in LLVM_GLOBS:
        for path in glob.glob(pattern):
            try:
                major = int(Path(path).name.split(".so.")[1].split(".")[0])
            except ValueError:
                continue
            if major >= 16:
                found.append((major, path))
    return max(found)[1] if found else None


def llvm_works(library: str | None) -> bool:
    """Whether Mitsuba's llvm variant runs a kernel with ``library`` (in a subprocess)."""
    env = dict(os.environ)
    if library:
        env["DRJIT_LIBLLVM_PATH"] = library
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                              text=True, timeout=120)
    except subprocess.TimeoutExpired:
        return False
    return done.returncode == 0


def variant(requested: str = "auto", log=print) -> str:
    """The Mitsuba variant to render with, set in this process.

    ``auto``: ``llvm_ad_rgb`` where it works, else ``scalar_rgb`` (said through ``log``);
    another name is set as asked (``cuda_ad_rgb`` on a GPU). The llvm variants need
    ``DRJIT_LIBLLVM_PATH`` before Mitsuba is imported: set here from :func:`llvm_library`.
    """
    library = llvm_library()
    if library and "DRJIT_LIBLLVM_PATH" not in os.environ and "mitsuba" not in sys.modules:
        os.environ["DRJIT_LIBLLVM_PATH"] = library
    mi, _ = import_mitsuba()
    chosen = requested
    if requested == "auto":
        if llvm_works(library):
            chosen = "llvm_ad_rgb"
        else:
            chosen = "scalar_rgb"
            log("mitsuba: the llvm variant needs LLVM 16 or later (found "
                f"{library or 'none'}; on Debian 12: apt-get install libllvm19): rendering "
                "with scalar_rgb, one sample at a time in Python (slow)")
    if chosen not in mi.variants():
        raise BTFError(f"Mitsuba variant {chosen!r} is not available (have: "
                       f"{', '.join(mi.variants())})")
    mi.set_variant(chosen)
    return chosen


def tables(path: str | Path, rank: int | None = None, *, size: tuple[int, int] | None = None,
           origin: tuple[int, int] = (0, 0), seed: int | None = None, level: int = 0):
    """The :class:`tasks.btf_bsdf.Tables` of a compressed store or compressed tile set.

    A store's factors are held in memory. A tile set's surface is laid over the texels
    ``origin`` to ``origin + size`` (default: one sample's size from 0) exactly as ``btf
    render`` lays it (:mod:`tasks.placement`, the tile set's seed unless ``seed``), and that
    region's eigentextures are what the BSDF's texture holds (``size x rank`` values).
    ``level`` N: the eigentextures' means over blocks of 2^N texels a side, as ``btf view
    --level`` shows them (:func:`tasks.viewer.block_means`).
    """
    from pipeline.stores import CompressedStore, CompressedTileSetStore, TileSetStore, open_store
    from pipeline.stores.radiance import as_float32
    from tasks.btf_bsdf import Tables
    from tasks.viewer import block_means, mesh

    store = open_store(path, CompressedStore, TileSetStore)
    if isinstance(store, TileSetStore) and not isinstance(store, CompressedTileSetStore):
        raise BTFError(f"{path}: a tile set of radiance tiles: the BSDF renders factors; quilt "
                       "a compressed store (btf compress, then btf quilt or btf roller on it)")
    group = store.group
    full = group["S"].shape[0]
    k = full if rank is None else int(rank)
    if not 1 <= k <= full:
        raise BTFError(f"{path}: rank {k} is not between 1 and the stored rank {full}")
    u = np.asarray(group["U"][..., :k], np.float32)
    s = np.asarray(group["S"][:k], np.float32)
    if isinstance(store, CompressedTileSetStore):
        v = surface_eigentextures(store, k, size=size, origin=origin, seed=seed)
    elif size is not None or tuple(origin) != (0, 0) or seed is not None:
        raise BTFError(f"{path}: a compressed store, not a tile set: a surface size, origin "
                       "or seed applies to tile sets")
    else:
        v = as_float32(group["V"][..., :k]).astype(np.float32)
    if level < 0 or 2**level > min(v.shape[:2]):
        raise BTFError(f"{path}: level {level} is out of range (the texture is "
                       f"{v.shape[0]} x {v.shape[1]} texels)")
    v = block_means(v, 2**level)
    d = store.directions
    try:
        views = mesh(d.theta_view, d.phi_view, "view")
        lights = mesh(d.theta_light, d.phi_light, "light")
    except ValueError as exc:
        raise BTFError(f"{path}: {exc}") from None
    transform = store.transform
    return Tables(us=u * s, v=v, view_mesh=views, light_mesh=lights, transform=transform,
                  scale=transform.layer_scale(d.theta_light))


def surface_eigentextures(tileset, rank: int, *, size: tuple[int, int] | None = None,
                          origin: tuple[int, int] = (0, 0), seed: int | None = None
                          ) -> np.ndarray:
    """``(y, x, rank)`` eigentextures of the surface a compressed tile set lays over a region.

    The same placement as ``btf render`` (:func:`pipeline.graphs.surface.lazy_layer`): corner
    tiles by the hash of their lattice vertices, the roller's tiles on their lattice.
    """
    from tasks.placement import gather, lattice_gather

    if size is None:
        size = tuple(tileset.sample_shape)
    seed = tileset.seed if seed is None else seed
    lattice = tileset.placement == "lattice"
    order = None if lattice else tileset.order()
    tiles = tileset.tile_eigentextures(range(tileset.tiles), rank)
    if order is not None:
        tiles = tiles[order]
    (y0, x0), (ny, nx) = origin, size
    if lattice:
        return lattice_gather(tiles, y0, x0, ny, nx, hnf=tileset.hnf, basis=tileset.basis,
                              representative=tileset.representative, seed=seed)
    return gather(tiles, y0, x0, ny, nx, seed=seed, corners=tileset.corner_types)


def bsdf(path: str | Path, rank: int | None = None, uv_scale: float = 1.0, **surface):
    """A ``btf`` BSDF object of the active variant for a compressed store or tile set.

    ``surface``: ``level``, and a tile set's ``size``, ``origin`` and ``seed`` (:func:`tables`).
    """
    mi, dr = import_mitsuba()
    from tasks.btf_bsdf import bsdf_class

    props = mi.Properties("btf")
    props["uv_scale"] = float(uv_scale)
    return bsdf_class(mi, dr)(props, tables(path, rank, **surface))


def register() -> None:
    """Register the ``btf`` BSDF with the active variant: scene files may then name it.

    Its parameters: ``store`` (string, a compressed store or compressed tile set), ``rank``
    (integer, default all), ``uv_scale`` (float, default 1: texture repeats per unit of uv),
    ``level`` (integer, default 0: blocks of 2^level texels, as ``btf view --level``),
    and for a tile set ``size`` ("H,W" texels of its surface, default the sample's),
    ``origin`` ("Y,X", default 0,0) and ``seed`` (default the tile set's).
    """
    mi, dr = import_mitsuba()
    from tasks.btf_bsdf import bsdf_class

    cls = bsdf_class(mi, dr)

    def make(props):
        rank = int(props.get("rank", 0)) or None  # 0: every stored component
        surface = {}
        for name in ("size", "origin"):  # "H,W" and "Y,X" texels of a tile set's surface
            text = str(props.get(name, ""))
            if text:
                surface[name] = tuple(int(v) for v in text.split(","))
        if int(props.get("seed", -1)) >= 0:
            surface["seed"] = int(props.get("seed", -1))
        surface["level"] = int(props.get("level", 0))
        return cls(props, tables(props["store"], rank, **surface))

    mi.register_bsdf("btf", make)
