"""Periodicity detection on lattices nobody tuned it on: random orientations, oblique cells,
four motifs, noise, illumination gradients, non-square images; and no false positives."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from skimage import data

from benchmarks.lattices import MOTIFS, judge, random_lattice_texture, stochastic_texture
from tasks.materials import Material
from tasks.periodicity import detect_lattice

THRESHOLD = 0.5  # btf roller's default --min-confidence


# All 200 lattices (the rate of BENCHMARKS.md: 97%, and 90% of every motif) in the slow set;
# the first 32 of them in the default set, where its two misses are already 6% (both are
# "lines" cases of the 200, 2 of that motif's 8 here): a broken detector finds far fewer.
@pytest.mark.parametrize(("count", "rate", "motif_rate"),
                         [(32, 0.9, 0.75), pytest.param(200, 0.97, 0.9, marks=pytest.mark.slow)])
def test_random_lattices_give_their_primitive_cell(count, rate, motif_rate):
    rng = np.random.default_rng(20261123)  # not a seed the detector was developed on
    found, total, failures = Counter(), Counter(), []
    for i in range(count):
        case = random_lattice_texture(rng, motif=MOTIFS[i % len(MOTIFS)])
        lattice = detect_lattice(case.image)
        good = lattice.confidence >= THRESHOLD and judge(lattice.u, lattice.v, case.u, case.v)
        found[case.motif] += good
        total[case.motif] += 1
        if not good:
            failures.append(f"{case.describe()}: found {lattice.u}, {lattice.v} "
                            f"({lattice.confidence:.2f})")
    assert sum(found.values()) >= rate * count, "\n".join(failures)
    for motif in MOTIFS:
        assert found[motif] >= motif_rate * total[motif], (motif, failures)


def test_judging_is_basis_independent_and_rejects_wrong_cells():
    u, v = np.array([3.0, 17.0]), np.array([15.0, -4.0])
    assert judge(u + v, 2 * u + v, u, v)  # another basis of the same lattice
    assert not judge(u, 2 * v, u, v)  # a sub-lattice: twice the cell
    assert not judge(u, v / 2, u, v)  # a finer lattice: v / 2 is off the lattice
    assert not judge(u + np.array([0.8, 0.8]), v, u, v)  # more than a pixel off


@pytest.mark.parametrize("noise", [0.0, 0.1])
def test_the_reported_rotated_rectangular_lattice_of_soft_blobs(noise):
    """The texture of the bug report: periods about 20 px rotated by 30 degrees, 256 x 256."""
    a = np.radians(30.0)
    u = 20.0 * np.array([np.sin(a), np.cos(a)])
    v = 23.0 * np.array([np.cos(a), -np.sin(a)])
    yy, xx = np.mgrid[0:256, 0:256].astype(float)
    coef = np.einsum("ij,jyx->iyx", np.linalg.inv(np.stack([u, v], axis=1)), np.stack([yy, xx]))
    d = np.einsum("iyx,ij->yxj", coef - np.rint(coef), np.stack([u, v]))
    image = np.exp(-0.5 * (d ** 2).sum(-1) / 4.0 ** 2)
    image += noise * np.random.default_rng(0).standard_normal(image.shape)
    lattice = detect_lattice(image)
    assert lattice.confidence > 0.8
    assert judge(lattice.u, lattice.v, u, v, px=0.3)


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb[..., :3].astype(float) @ np.array([0.2126, 0.7152, 0.0722])


def _stochastic():
    rng = np.random.default_rng(7)
    for k in range(4):
        yield f"noise-{k}", stochastic_texture(rng, "noise", (192 + 32 * k, 256))
    for k in range(8):
        yield f"fbm-{k}", stochastic_texture(rng, "fbm", (256, 160 + 32 * k))
    for seed in range(4):
        albedo = Material("stone", seed=seed).fields(0, 0, 256, 224).albedo
        yield f"stone-{seed}", _luminance(albedo)
    yield "leather", _luminance(Material("leather", seed=1).fields(0, 0, 256, 256).albedo)
    yield "gravel (photo)", data.gravel().astype(float)
    yield "grass (photo)", data.grass().astype(float)


def test_no_false_positive_on_stochastic_textures():
    confidences = {name: detect_lattice(image).confidence for name, image in _stochastic()}
    assert max(confidences.values()) < THRESHOLD, confidences

