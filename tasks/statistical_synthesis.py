"""Statistical synthesis on a steerable pyramid (Portilla and Simoncelli 2000; paper 000, 3.1).

Texture Optimization averages overlapping neighbourhoods and loses fine detail; the paper
restores it by imposing the sample's wavelet statistics on the result. Each coefficient channel
(one eigentexture, ``Sigma V^T`` of one component) is treated as a grey image: the eigentextures
are uncorrelated over the sample by construction (the columns of ``V`` are orthogonal), so the
channels are synthesized independently.

The statistics are measured on a real steerable pyramid (pyrtools' ``SteerablePyramidFreq``:
``height`` scales, 4 orientations, periodic boundaries) of the sample's channel, and imposed on
the result's by alternating projections, ``iterations`` times. **Statistic groups imposed:**

- **pixel marginals**: the whole histogram of the channel's values (so its mean, variance,
  skewness, kurtosis, minimum and maximum), by histogram matching after reconstruction;
- **subband marginals**: the whole histogram of every oriented band at every scale and of the
  high-pass residual (so each band's variance, skewness and kurtosis), by histogram matching;
- **autocorrelation of the low-pass band**: the central ``(2 M + 1)^2`` autocorrelation of the
  low-pass residual (``M = 3``, PS's 7 x 7), by scaling its spectrum with the ratio of the
  spectra of the target and current central autocorrelations, then its histogram.

**Not imposed** (PS's other groups): magnitude correlations across orientations and scales,
cross-scale phase statistics, and the autocorrelation of the intermediate low-pass scales.
Histogram matching imposes more than PS's four moments per band; the structure those
correlation groups carry comes here from Texture Optimization, whose neighbourhoods are
copies of the sample's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.errors import InvalidParameter

LAGS = 3  # central autocorrelation of the low-pass band: (2 LAGS + 1)^2 lags, as PS


@dataclass(frozen=True)
class StatisticsParams:
    """Pyramid height (None: as many scales as the smaller image allows) and iterations."""

    height: int | None = None
    iterations: int = 2

    def __post_init__(self):
        if self.height is not None and self.height < 1:
            raise InvalidParameter("height", f"height must be at least 1, got {self.height}")
        if self.iterations < 1:
            raise InvalidParameter("iterations",
                                   f"iterations must be at least 1, got {self.iterations}")


def pyramid_height(shape_a: tuple[int, ...], shape_b: tuple[int, ...], wanted: int | None
                   ) -> int:
    """Scales both images allow: their low-pass residual keeps at least 8 texels a side."""
    allowed = max(1, int(np.floor(np.log2(min(*shape_a[:2], *shape_b[:2]) / 8))))
    return allowed if wanted is None else min(wanted, allowed)


def _pyramid(image: np.ndarray, height: int):
    """The pyramid of ``image`` mirrored out to a multiple of ``2^height`` texels a side.

    pyrtools reconstructs exactly only sizes that halve evenly at every scale; odd or
    non-dyadic images are extended by reflection (no new edge), and callers crop back.
    """
    import pyrtools as pt

    image = np.asarray(image, np.float64)
    step = 2**height
    pad = [(0, -n % step) for n in image.shape]
    if any(after for _, after in pad):
        image = np.pad(image, pad, mode="symmetric")
    return pt.pyramids.SteerablePyramidFreq(image, height=height, order=3)


@dataclass(frozen=True)
class ChannelStatistics:
    """What is imposed on one channel: the sample's pixels, bands and low-pass autocorrelation."""

    pixels: np.ndarray
    bands: dict
    lowpass_autocorrelation: np.ndarray
    height: int


def measure(reference: np.ndarray, height: int) -> ChannelStatistics:
    """The statistics of a sample channel (a 2-D image) on a pyramid of ``height`` scales."""
    pyr = _pyramid(reference, height)
    bands = {key: np.asarray(band) for key, band in pyr.pyr_coeffs.items()}
    return ChannelStatistics(np.asarray(reference, np.float64), bands,
                             central_autocorrelation(bands["residual_lowpass"]), height)


def central_autocorrelation(image: np.ndarray, lags: int = LAGS) -> np.ndarray:
    """``(2 lags + 1)^2`` circular autocorrelation of ``image`` minus its mean, per texel."""
    x = np.asarray(image, np.float64)
    x = x - x.mean()
    spectrum = np.fft.fft2(x)
    ac = np.real(np.fft.ifft2(spectrum * np.conj(spectrum))) / x.size
    ac = np.fft.fftshift(ac)
    cy, cx = ac.shape[0] // 2, ac.shape[1] // 2
    ly, lx = min(lags, cy), min(lags, cx)
    out = np.zeros((2 * lags + 1, 2 * lags + 1))
    out[lags - ly : lags + ly + 1, lags - lx : lags + lx + 1] = ac[cy - ly : cy + ly + 1,
                                                                   cx - lx : cx + lx + 1]
    return out


def _spectrum_of(ac: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The smoothed power spectrum an autocorrelation window stands for, on a ``shape`` grid.

    The lags are tapered by a triangular (Bartlett) window first: the periodogram convolved
    with a Fejer kernel, which is never negative (a window cut square is, and its small or
    negative values made the spectral ratio explode).
    """
    lags = ac.shape[0] // 2
    taper = 1.0 - np.abs(np.arange(-lags, lags + 1)) / (lags + 1)
    tapered = ac * np.outer(taper, taper)
    embedded = np.zeros(shape)
    for i in range(-lags, lags + 1):
        for j in range(-lags, lags + 1):
            embedded[i % shape[0], j % shape[1]] += tapered[i + lags, j + lags]
    return np.maximum(np.real(np.fft.fft2(embedded)), 0.0)


def impose_autocorrelation(image: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Scale ``image``'s spectrum so its central autocorrelation moves to ``target``.

    The gain is the square root of the ratio of the two (smoothed) spectra, where both carry
    power (above a millionth of their peak); elsewhere the spectrum is left as it is.
    """
    x = np.asarray(image, np.float64)
    mean = x.mean()
    current = central_autocorrelation(x, target.shape[0] // 2)
    want = _spectrum_of(target, x.shape)
    have = _spectrum_of(current, x.shape)
    floor = 1e-6 * max(float(want.max()), float(have.max()), 1e-300)
    gain = np.where((want > floor) & (have > floor), np.sqrt(want / np.maximum(have, floor)),
                    1.0)
    return np.real(np.fft.ifft2(np.fft.fft2(x - mean) * gain)) + mean


def impose(image: np.ndarray, stats: ChannelStatistics, *, iterations: int) -> np.ndarray:
    """Impose a sample channel's statistics (see the module) on a channel of any size."""
    from skimage.exposure import match_histograms

    x = np.asarray(image, np.float64)
    for _ in range(iterations):
        pyr = _pyramid(x, stats.height)
        for key, band in pyr.pyr_coeffs.items():
            if key == "residual_lowpass":
                band = impose_autocorrelation(band, stats.lowpass_autocorrelation)
            pyr.pyr_coeffs[key] = match_histograms(band, stats.bands[key])
        x = match_histograms(pyr.recon_pyr()[: x.shape[0], : x.shape[1]], stats.pixels)
    return x


def sample_statistics(sample: np.ndarray, shape: tuple[int, int], *, params: StatisticsParams,
                      channels: int | None = None) -> list[ChannelStatistics]:
    """The statistics of a sample's channels for images of ``shape`` (the pyramid both allow).

    ``channels``: only the first ones (the leading components).
    """
    sample = np.asarray(sample, np.float32)
    height = pyramid_height(shape, sample.shape, params.height)
    count = sample.shape[-1] if channels is None else min(channels, sample.shape[-1])
    return [measure(sample[..., k], height) for k in range(count)]


def impose_statistics(image: np.ndarray, statistics: list[ChannelStatistics], *,
                      iterations: int) -> np.ndarray:
    """Impose measured channel statistics on ``image`` (``(H, W, K)``; float32 result).

    Channels beyond the measured ones pass through.
    """
    out = np.array(image, np.float32)
    for k, stats in enumerate(statistics):
        out[..., k] = impose(out[..., k], stats, iterations=iterations)
    return out
