"""Where the enlargement's error goes: cast-shadowed against lit pairs (issue 57, a study).

``python -m benchmarks.shadow_split bumps:1,stone:5 [SETS]``: for each ``material:seed``, the
enlargement bench's case (:func:`benchmarks.enlarge._material`: a 128^2 truth under btf's
shading, ``abtf:12,4``, its central 64^2 at rank 16) enlarged under each photo set of
``SETS`` (default ``top,random``: one photo, ten). Every (texel, light) pair outside the
sample is classed by the truth's cast shadow there (:func:`tasks.heightfield.visibility` of
the truth's height field with the store's shading parameters; under 0.5 of the light:
shadowed), and the RMS radiance error of the result and of the copy oracle is given per
class, per light elevation, with the share of the squared error the shadowed pairs carry.
One JSON line a case. Not a ``btf bench`` suite: a study whose figures are in BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.enlarge import PHOTO_MATERIALS, _factors, _material, material_seeds, truth_rows
from tasks.evaluation import gap_share, oracle
from tasks.heightfield import visibility
from tasks.materials import Material
from tasks.svd import reconstruct

SIZE = 128
HALO = 40  # texels of height beyond the store's edge: past the longest shadow (32 at 78.75)


def _radiance(u: np.ndarray, coefficients: np.ndarray, transform) -> np.ndarray:
    """``(H, W, rows)`` linear radiance of per-texel coefficients in the basis ``u``."""
    rank = coefficients.shape[-1]
    flat = coefficients.reshape(-1, rank)
    return reconstruct(u, np.ones(rank), flat, transform=transform).T.reshape(
        *coefficients.shape[:2], -1)


def _visibility(name: str, group) -> np.ndarray:
    """``(H, W, lights)``: the share of each light reaching each texel of the truth."""
    shading = group.attrs["shading"]
    if name in PHOTO_MATERIALS:  # btf generate mirrors a photo's fields at its borders
        height = np.pad(group["height"][...], HALO, mode="reflect")
    else:  # a procedural material's fields are defined beyond the store
        material = group.attrs["material"]
        height = Material(name, material["seed"], material.get("scale")).fields(
            -HALO, -HALO, SIZE + 2 * HALO, SIZE + 2 * HALO).height
    height = height.astype(np.float32)
    return np.stack([visibility(height, HALO, HALO, SIZE, SIZE, theta=float(t), phi=float(p),
                                relief=shading["relief"], penumbra=shading["penumbra"],
                                max_length=shading["max_shadow"])
                     for t, p in zip(group["theta_light"][...], group["phi_light"][...],
                                     strict=True)], axis=-1)


def _split(estimate: np.ndarray, truth: np.ndarray, shadowed: np.ndarray,
           elevation: np.ndarray) -> dict:
    """RMS error over lit and shadowed pairs, overall and per light elevation."""
    lights = shadowed.shape[-1]
    squared = ((estimate.reshape(-1, lights, 3) - truth.reshape(-1, lights, 3)) ** 2).mean(-1)
    row = {"rms_lit": np.sqrt(squared[~shadowed].mean()),
           "rms_shadowed": np.sqrt(squared[shadowed].mean()),
           "shadowed_share_of_squared_error": squared[shadowed].sum() / squared.sum()}
    for theta in np.unique(elevation):
        for label, pick in (("lit", ~shadowed), ("shadowed", shadowed)):
            chosen = pick & (elevation == theta)
            row[f"{label}_{theta:g}"] = np.sqrt(squared[chosen].mean()) if chosen.any() else None
    return {k: None if v is None else round(float(v), 4) for k, v in row.items()}


def case(name: str, seed: int, sets: str) -> dict:
    """One material and seed: the split of the result's and the oracle's error."""
    import zarr

    folder = Path(tempfile.mkdtemp(prefix="btf-shadow-split-"))
    try:
        args = argparse.Namespace(size=SIZE, rank=16, sets=sets, baselines="lookup", seed=seed,
                                  enlarge_options="", sheet=None)
        bench = _material(name, args, folder, ())
        group = zarr.open_group(folder / "M.zarr", mode="r")
        mask = np.ones((SIZE, SIZE), bool)
        mask[SIZE // 4 : 3 * SIZE // 4, SIZE // 4 : 3 * SIZE // 4] = False
        shadowed = _visibility(name, group)[mask] < 0.5
        elevation = np.broadcast_to(group["theta_light"][...], shadowed.shape)
        truth = truth_rows(folder / "M.zarr")
        us, ss, vs, transform, _ = _factors(folder / "S_svd.zarr")
        u = us.reshape(truth.shape[-1], len(ss))
        copy, _ = oracle(u, vs * ss.astype(np.float32), transform, truth)
        out = {"case": f"{name}:{seed}", "shadowed_pairs": round(float(shadowed.mean()), 3),
               "shadowed_pairs_by_elevation": {
                   f"{t:g}": round(float(shadowed[elevation == t].mean()), 3)
                   for t in np.unique(elevation)},
               "oracle": _split(_radiance(u, copy, transform)[mask], truth[mask], shadowed,
                                elevation)}
        for which in sets.split(","):
            ue, se, ve, _, _ = _factors(folder / f"E_{which}.zarr")
            result = _radiance(ue.reshape(u.shape), ve * se.astype(np.float32), transform)
            row = bench["sets"][which]
            out[which] = {"gap": round(gap_share(row["final"]["error"], row["lookup"]["error"],
                                                 row["oracle"]["error"]), 3),
                          **_split(result[mask], truth[mask], shadowed, elevation)}
        return out
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) not in (1, 2):
        print(__doc__.split("\n\n")[1], file=sys.stderr)
        return 2
    sets = argv[1] if len(argv) > 1 else "top,random"
    for name, seed in material_seeds(argv[0]):
        print(json.dumps(case(name, seed, sets)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
