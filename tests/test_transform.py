"""tasks.transform: how stored values decode to radiance, and back."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.svd import reconstruct, reconstruct_layers
from tasks.transform import NAMES, YUV_TO_RGB, Transform, dfmf_colour_matrix


def _radiance(rng, shape):
    # HDR-like: a few decades, some zeros, RGB with a colour cast
    r = np.exp(rng.normal(-2.0, 1.5, size=shape)).astype(np.float32)
    r[rng.random(shape) < 0.05] = 0.0
    return r


@pytest.mark.parametrize("name", NAMES)
def test_encode_then_decode_gives_back_the_radiance(name):
    rng = np.random.default_rng(5)
    radiance = _radiance(rng, (7, 5, 3))
    t = Transform(name, 1e-5 if name != "log" else 1e-3)
    back = t.decode(t.encode(radiance))
    # float32 round trip; U, V of the YUV models are relative to Y + eps
    assert np.allclose(back, radiance, rtol=2e-5, atol=2e-6), np.abs(back - radiance).max()


def test_the_yuv_models_decode_as_bonns_readers_write_them():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(4, 3)).astype(np.float32) * 0.5
    eps = 1e-5
    y = np.exp(a[:, 0]) - eps
    expected = {  # btflib undecorrelate.m, written out per model
        "ylog-uv": np.stack([y, a[:, 1], a[:, 2]], 1) @ YUV_TO_RGB.T,
        "ylog-uv-over-y": np.stack([y, a[:, 1] * (y + eps), a[:, 2] * (y + eps)], 1)
        @ YUV_TO_RGB.T,
        "ylog-ulog-vlog": np.stack([y, *(np.sign(a[:, c]) * np.exp(np.abs(a[:, c]) + np.log(eps))
                                         for c in (1, 2))], 1) @ YUV_TO_RGB.T,
    }
    for name, rgb in expected.items():
        got = Transform(name, eps).decode(a.copy())
        assert np.allclose(got, np.maximum(rgb, 0), rtol=1e-5, atol=1e-6), name
    # the channel axis may be anywhere; a wrong channel count is refused
    moved = Transform("ylog-uv-over-y", eps).decode(a.T.copy(), axis=0)
    assert np.allclose(moved.T, np.maximum(expected["ylog-uv-over-y"], 0), rtol=1e-5,
                       atol=1e-6)
    with pytest.raises(ValueError, match="3 channels"):
        Transform("ylog-uv", eps).decode(np.zeros((2, 4), np.float32))


def test_reconstruct_decodes_whole_layers_of_channels():
    rng = np.random.default_rng(2)
    u = rng.normal(size=(2, 5, 3, 4)).astype(np.float32) * 0.3  # view, light, channel, k
    s = np.array([3.0, 2.0, 1.0, 0.5], np.float32)
    v = rng.normal(size=(6, 7, 4)).astype(np.float32) * 0.3
    t = Transform("ylog-uv-over-y", 1e-5)
    values = np.einsum("vlck,k,yxk->vlyxc", u, s, v)
    assert np.allclose(reconstruct_layers(u, s, v, transform=t), t.decode(values), rtol=1e-5,
                       atol=1e-6)
    flat = reconstruct(u.reshape(-1, 4), s, v.reshape(-1, 4), transform=t)  # rows: (v, l, c)
    assert np.allclose(flat.reshape(2, 5, 3, 6, 7), np.moveaxis(t.decode(values), -1, 2),
                       rtol=1e-5, atol=1e-6)


def test_linear_colour_models_fold_into_one_matrix():
    rng = np.random.default_rng(3)
    yuv = rng.normal(size=(5, 3))
    m, mean = dfmf_colour_matrix(1, np.eye(3), np.zeros(3), 3)
    assert np.allclose(yuv @ m + mean, yuv @ YUV_TO_RGB.T)
    pca, pmean = rng.normal(size=(3, 3)), rng.normal(size=3)
    m, mean = dfmf_colour_matrix(3, pca, pmean, 3)
    assert np.allclose(yuv @ m + mean, yuv @ pca + pmean)
    m, _ = dfmf_colour_matrix(0, np.eye(3), np.zeros(3), 5)
    assert np.array_equal(m, np.eye(5))
    with pytest.raises(ValueError, match="not linear"):
        dfmf_colour_matrix(11, np.eye(3), np.zeros(3), 3)


def test_old_stores_without_a_name_are_the_log_transform():
    assert Transform.from_attrs({"eps": 0.01}) == Transform("log", 0.01)
    with pytest.raises(ValueError, match="unknown transform"):
        Transform("gamma", 1.0)


@pytest.mark.parametrize("name", ["log", "linear", "ylog-uv", "ylog-ulog-vlog", "ylog-uv-over-y"])
@pytest.mark.parametrize("cosine", [False, True])
def test_compiled_layers_equal_numpys_decode_and_layout(name, cosine):
    """reconstruct_layers' compiled decode against the rows' numpy decode, moved by numpy."""
    from tasks.svd import FUSED_DECODE, reconstruct, reconstruct_layers

    rng = np.random.default_rng(3)
    u = rng.normal(scale=0.6, size=(2, 5, 3, 7)).astype(np.float32)
    u[0, 0, :, 0] = 40.0  # above LOG_MAX after the product: clamped, not inf
    s = rng.uniform(0.5, 2.0, 7).astype(np.float32)
    side = int(np.ceil(np.sqrt(FUSED_DECODE / 30))) + 1  # large enough for the kernel
    v = rng.normal(scale=0.5, size=(side, side, 7)).astype(np.float32)
    transform = Transform(name, 1e-3, cosine)
    scale = rng.uniform(1.0, 3.0, (2, 5)).astype(np.float32) if cosine else None
    got = reconstruct_layers(u, s, v, transform=transform, scale=scale)
    rows = None if scale is None else np.repeat(scale.reshape(-1), 3)
    want = np.moveaxis(reconstruct(u.reshape(-1, 7), s, v.reshape(-1, 7), transform=transform,
                                   scale=rows).reshape(2, 5, 3, side, side), 2, -1)
    assert got.shape == want.shape == (2, 5, side, side, 3) and got.dtype == np.float32
    assert np.isfinite(got).all() and (got >= 0).all()
    # exp's last bit differs (libm's, numpy's); the YUV models' sums cancel near 0, so the
    # bound is relative to the layers' scale there
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=2e-6 * float(np.abs(want).max()))
