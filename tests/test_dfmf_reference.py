"""The test DFMF writer (tests/dfmf_files.py) against an independent reader, btf-extractor.

btf-extractor 1.7.0 lives in .venv-btfx (installed by .ci/run); without it these tests skip,
unless BTF_REQUIRE_BTFX=1 (CI's slow run), where they fail. Its quirks (row flip, BGR,
clamping in model 11 only, ``U = c1 * Y + eps``) are documented in tests/btfx.py.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from btfx import as_store_layers, btfx_available, btfx_images, btfx_time
from dfmf_files import (
    EPS,
    SCALAR_DTYPES,
    YUV_TO_RGB,
    reference_decode,
    resigned_copy,
    truncated_copy,
    write_dfmf,
)

pytestmark = pytest.mark.slow

W, H = 8, 6  # non-square: a transposed texel order cannot pass
# Degrees, as (theta, phi) with phi in (-180, 180] as in the file. A view at theta 0 with a
# phi of 120: btf-extractor keys it as phi 180 (tests/btfx.py matches the nearest key).
VIEWS = [(0.0, 120.0), (30.0, -150.0), (60.0, 45.0)]
LIGHTS = [(11.0, 15.0), (37.5, 7.5), (75.0, -90.0)]
PAIRS = [(tl, pl, tv, pv) for tv, pv in VIEWS for tl, pl in LIGHTS]  # view-major, like rows
RAD_VIEWS = [tuple(np.deg2rad(a)) for a in VIEWS]
RAD_LIGHTS = [tuple(np.deg2rad(a)) for a in LIGHTS]
ROWS = len(VIEWS) * len(LIGHTS)
TOL = {"rtol": 1e-5, "atol": 1e-5}


@pytest.fixture(scope="module", autouse=True)
def _btfx():
    if not btfx_available():
        msg = ("btf-extractor is not installed in .venv-btfx (the install commands are in "
               ".ci/run)")
        if os.environ.get("BTF_REQUIRE_BTFX") == "1":
            pytest.fail(f"BTF_REQUIRE_BTFX=1 but {msg}")
        pytest.skip(msg)


def quantized(mats, scalar_size):
    return [np.asarray(m).astype(SCALAR_DTYPES[scalar_size]).astype(np.float64) for m in mats]


def factors_rgb(rng, ks):
    """Asymmetric random factors whose products span about [-3, 3]: model 0, unclamped."""
    u = [rng.uniform(-1.0, 1.5, (ROWS, k)) for k in ks]
    sxv = [rng.uniform(-0.8, 1.0, (W * H, k)) for k in ks]
    return u, sxv


def factors_model11(rng, ks):
    """c0 = log(Y) with Y in about [0.25, 0.8], small chroma; two texels that clamp."""
    u = [rng.uniform(-0.5, 0.6, (ROWS, k)) for k in ks]
    sxv = [rng.uniform(-0.3, 0.25, (W * H, k)) * (1.0 if c == 0 else 0.4)
           for c, k in enumerate(ks)]
    u[0][:, 0] = 1.0
    sxv[0][:, 0] = np.log(0.45)
    sxv[0][1] = 0.0
    sxv[0][1, 0] = np.log(3.0)  # texel (1, 0): Y = 3, clamps to 1
    sxv[1][1] = sxv[2][1] = 0.0
    sxv[0][W + 2] = 0.0
    sxv[0][W + 2, 0] = np.log(1e-3)  # texel (2, 1): B = Y (1 + 2.03 U / Y) < 0, clamps to 0
    sxv[1][W + 2] = 0.0
    sxv[1][W + 2, 0] = -0.9
    u[1][:, 0] = 1.0
    return u, sxv


def btfx_model11(c):
    """btf-extractor's model 11 on channel sums c (..., 3): U = c1 * Y + eps, clamped."""
    y = np.exp(c[..., 0]) - EPS
    yuv = np.stack([y, c[..., 1] * y + EPS, c[..., 2] * y + EPS], axis=-1)
    return np.clip(yuv @ YUV_TO_RGB.T, 0.0, 1.0)


def assert_matches_only(got, expected):
    """``got`` equals ``expected`` (views, lights, H, W, 3) and no scrambled variant of it."""
    np.testing.assert_allclose(got, expected, **TOL)
    v, lt = len(VIEWS), len(LIGHTS)
    scrambled = {
        "lights and views swapped": expected.reshape(lt, v, H, W, 3).swapaxes(0, 1),
        "texels transposed (x slowest)":
            expected.reshape(v, lt, W, H, 3).swapaxes(2, 3),
        "rows not flipped": expected[:, :, ::-1],
        "RGB instead of BGR": expected[..., ::-1],
    }
    for what, wrong in scrambled.items():
        assert np.abs(got - wrong).max() > 1e-2, f"the test cannot tell {what}"


def decode_btfx(path):
    got = as_store_layers(btfx_images(path, PAIRS))
    return got.reshape(len(VIEWS), len(LIGHTS), H, W, 3).astype(np.float64)


@pytest.mark.parametrize(("scalar_size", "ks", "version", "rotations"), [
    (2, (2, 5, 3), 4, False),
    (4, (4, 3, 2), 4, True),
    (8, (3, 3, 5), 1, False),
    (2, (9, 2, 4), 3, True),  # k = 9: btf-extractor's 8-wide float16 loop plus a remainder
])
def test_rgb_model_matches_btf_extractor(tmp_path, scalar_size, ks, version, rotations):
    rng = np.random.default_rng(sum(ks) * 10 + scalar_size)
    u, sxv = factors_rgb(rng, ks)
    path = write_dfmf(tmp_path / "rgb.btf", views=RAD_VIEWS, lights=RAD_LIGHTS, u=u, sxv=sxv,
                      width=W, height=H, color_model=0, scalar_size=scalar_size,
                      version=version, rotations=rotations, xml="<btf>test</btf>")
    expected = reference_decode(quantized(u, scalar_size), quantized(sxv, scalar_size),
                                color_model=0, width=W, height=H, lights=RAD_LIGHTS)
    assert expected.min() < -0.5 and expected.max() > 1.5  # model 0 is not clamped
    assert_matches_only(decode_btfx(path), expected)


@pytest.mark.parametrize(("scalar_size", "ks"), [(2, (5, 2, 3)), (4, (3, 4, 2))])
def test_model11_matches_btf_extractor(tmp_path, scalar_size, ks):
    rng = np.random.default_rng(7 + scalar_size)
    u, sxv = factors_model11(rng, ks)
    path = write_dfmf(tmp_path / "m11.btf", views=RAD_VIEWS, lights=RAD_LIGHTS, u=u, sxv=sxv,
                      width=W, height=H, color_model=11, scalar_size=scalar_size)
    uq, vq = quantized(u, scalar_size), quantized(sxv, scalar_size)
    sums = reference_decode(uq, vq, color_model=0, width=W, height=H, lights=RAD_LIGHTS)
    expected = btfx_model11(sums)
    inside = (expected > 0) & (expected < 1)
    assert inside.mean() > 0.9 and (expected == 1).any() and (expected == 0).any()
    assert_matches_only(decode_btfx(path), expected)
    # btflib's U = c1 (Y + eps) against btf-extractor's c1 Y + eps: a few eps apart.
    ref = reference_decode(uq, vq, color_model=11, width=W, height=H, lights=RAD_LIGHTS)
    assert np.abs(np.clip(ref, 0, 1) - expected).max() < 1e-4


def test_btf_extractor_ignores_other_models_and_cosine(tmp_path):
    """Model 3 with a cosine flag: btf-extractor returns the bare channel sums."""
    rng = np.random.default_rng(3)
    u, sxv = factors_rgb(rng, (2, 3, 4))
    path = write_dfmf(tmp_path / "pca.btf", views=RAD_VIEWS, lights=RAD_LIGHTS, u=u, sxv=sxv,
                      width=W, height=H, color_model=3, scalar_size=4, cosine=True,
                      color_mean=(0.1, 0.2, 0.3), color_matrix=rng.normal(size=(3, 3)))
    sums = reference_decode(quantized(u, 4), quantized(sxv, 4), color_model=0, width=W,
                            height=H, lights=RAD_LIGHTS)
    np.testing.assert_allclose(decode_btfx(path), sums, **TOL)
    assert btfx_time(path, PAIRS[:2], repeat=2, threads=1) > 0


def test_btf_extractor_refuses_broken_files(tmp_path):
    rng = np.random.default_rng(5)
    u, sxv = factors_rgb(rng, (2, 2, 2))
    kw = {"views": RAD_VIEWS, "lights": RAD_LIGHTS, "u": u, "sxv": sxv, "width": W,
          "height": H}
    good = write_dfmf(tmp_path / "good.btf", **kw)
    bad = [
        truncated_copy(good, tmp_path / "truncated.btf", drop=3),
        resigned_copy(good, tmp_path / "signature.btf"),
        write_dfmf(tmp_path / "metasize.btf", metadata_size_delta=4, **kw),
        write_dfmf(tmp_path / "trailing.btf", trailing=b"\0", **kw),
        write_dfmf(tmp_path / "lightcount.btf", light_lists=[RAD_LIGHTS, RAD_LIGHTS[:2],
                                                             RAD_LIGHTS], **kw),
    ]
    assert btfx_images(good, PAIRS[:1]).shape == (1, H, W, 3)
    for path in bad:
        with pytest.raises(RuntimeError, match="btf-extractor failed"):
            btfx_images(path, PAIRS[:1])
