"""Realism without a neural network: a distance between texture statistics.

Per-texel error cannot say whether a result *looks like* the material: a blurred mean of the
right ABRDFs scores well on eq. (11) and looks wrong, and statistical synthesis raises that
error on purpose. This module measures what a viewer compares instead, the statistics
Portilla and Simoncelli (2000) showed to characterise a texture, on a real steerable pyramid
(pyrtools' ``SteerablePyramidFreq``, 4 orientations, periodic boundaries) of a grey image:

- **pixels**: mean, standard deviation, skewness, kurtosis, minimum and maximum;
- **bands**: per oriented band and scale, the log of its variance, its skewness and kurtosis,
  and the central 7 x 7 autocorrelation of its magnitude (normalised: what repeats, at which
  lags); the same for the low-pass residual (its raw autocorrelation);
- **magnitude correlations**: between the 4 orientations of a scale, and between each band's
  magnitude and the next coarser scale's (upsampled), as PS's cross-orientation and
  cross-scale groups.

:func:`realism` compares a result with the truth group by group (each group's RMS
difference, pixel values in units of the truth's standard deviation), divides each group's
distance by the same distance between two disjoint halves of the truth itself (its own
noise floor), and takes the RMS of these ratios: every group counts the same, and **1 means
as alike as the truth is to itself**; larger is less realistic. Measured on scikit-image's
brick, grass and gravel photos and a generated wood layer (log values, 256^2): another crop
of the same texture scores 0.8-2.1, the texture blurred by a Gaussian of 1.5 texels
2.4-5.7, its texels shuffled 4.1-6.5, a 64^2 crop of it repeated 1.5-2.5.
"""

from __future__ import annotations

import numpy as np

ORIENTATIONS = 4
LAGS = 3
FLOOR = 1e-3  # least noise floor of a group (two halves with equal statistics)


def log_luminance(rgb: np.ndarray) -> np.ndarray:
    """The grey image realism is measured on: ``log(max(Y, 0) + 1e-3)`` of linear RGB.

    ``rgb`` is ``(..., 3)``; ``Y`` its Rec. 709 luminance (:func:`tasks.reference.luminance`).
    """
    from tasks.reference import luminance

    return np.log(np.maximum(luminance(rgb), 0) + 1e-3)


def _pyramid(image: np.ndarray, height: int):
    import pyrtools as pt

    return pt.pyramids.SteerablePyramidFreq(np.asarray(image, np.float64), height=height,
                                            order=ORIENTATIONS - 1)


def _moments(x: np.ndarray) -> tuple[float, float, float]:
    x = x.ravel()
    sd = float(x.std())
    if sd == 0:
        return 0.0, 0.0, np.log(3.0)
    z = (x - x.mean()) / sd
    return sd, float(np.mean(z**3)), float(np.log(np.mean(z**4)))


def _autocorrelation(x: np.ndarray, lags: int = LAGS) -> np.ndarray:
    """Central ``(2 lags + 1)^2`` circular autocorrelation of ``x``, divided by its variance."""
    from tasks.statistical_synthesis import central_autocorrelation

    ac = central_autocorrelation(x, lags)
    return ac / max(float(ac[lags, lags]), 1e-300)


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
    norm = float(np.sqrt(np.dot(a, a) * np.dot(b, b)))
    return float(np.dot(a, b) / norm) if norm > 0 else 0.0


def height_for(shape: tuple[int, ...]) -> int:
    """Scales an image of ``shape`` allows with a low-pass residual of at least 8 texels."""
    return max(1, int(np.floor(np.log2(min(shape[:2]) / 8))))


def texture_statistics(image: np.ndarray, height: int | None = None) -> dict[str, np.ndarray]:
    """The statistic groups of the module for a grey image ``(h, w)`` (sides even at every scale).

    Pixel values are kept raw here; :func:`statistics_distance` scales them.
    """
    image = np.asarray(image, np.float64)
    height = height_for(image.shape) if height is None else height
    sd, skew, kurt = _moments(image)
    pyr = _pyramid(image, height)
    bands, autocorrelation, orientations, scales = [], [], [], []
    previous = None
    for scale in range(height):
        magnitudes = []
        for o in range(ORIENTATIONS):
            band = np.asarray(pyr.pyr_coeffs[(scale, o)])
            b_sd, b_skew, b_kurt = _moments(band)
            bands += [np.log(b_sd**2 + 1e-12), b_skew, b_kurt]
            magnitude = np.abs(band)
            autocorrelation.append(_autocorrelation(magnitude).ravel())
            magnitudes.append(magnitude)
        orientations += [_correlation(magnitudes[i], magnitudes[j])
                         for i in range(ORIENTATIONS) for j in range(i + 1, ORIENTATIONS)]
        if previous is not None:  # finer magnitudes against this scale's, upsampled
            scales += [_correlation(previous[o], np.kron(magnitudes[o], np.ones((2, 2)))
                                    [: previous[o].shape[0], : previous[o].shape[1]])
                       for o in range(ORIENTATIONS)]
        previous = magnitudes
    lowpass = np.asarray(pyr.pyr_coeffs["residual_lowpass"])
    high = np.asarray(pyr.pyr_coeffs["residual_highpass"])
    h_sd, h_skew, h_kurt = _moments(high)
    return {
        "pixels": np.array([image.mean(), sd, skew, kurt, image.min(), image.max()]),
        "bands": np.array([*bands, np.log(h_sd**2 + 1e-12), h_skew, h_kurt]),
        "autocorrelation": np.concatenate([*autocorrelation, _autocorrelation(lowpass).ravel()]),
        "orientations": np.array(orientations),
        "scales": np.array(scales),
    }


def group_distances(a: dict[str, np.ndarray], b: dict[str, np.ndarray], scale: float
                    ) -> dict[str, float]:
    """Each statistic group's RMS difference between two images' statistics.

    ``scale``: the reference's pixel standard deviation; pixel mean, standard deviation,
    minimum and maximum are compared in its units, skewness and kurtosis as they are.
    """
    scale = max(float(scale), 1e-12)
    units = np.array([scale, scale, 1.0, 1.0, scale, scale])
    return {key: float(np.sqrt(np.mean(((a[key] - b[key]) / (units if key == "pixels"
                                                                 else 1.0)) ** 2)))
            for key in a if len(a[key])}


def halves(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Top and bottom halves of ``(h, w, ...)``, cut to sides that halve at every scale."""
    h, w = image.shape[:2]
    half = h // 2
    height = height_for((half, w))
    step = 2**height
    hh, ww = half // step * step, w // step * step
    return image[:hh, :ww], image[half : half + hh, :ww]


def realism(result: np.ndarray, truth: np.ndarray) -> float:
    """How far ``result``'s statistics are from ``truth``'s, in units of the truth's own spread.

    Both are grey images of one size. Each half of the result is compared with the other
    half of the truth, group by group, and each group's distance is divided by the distance
    between the truth's two halves (its noise floor); the figure is the RMS of these ratios
    over the groups. A result equal to the truth scores exactly 1.
    """
    result_top, result_bottom = halves(np.asarray(result, np.float64))
    truth_top, truth_bottom = halves(np.asarray(truth, np.float64))
    rt, rb, tt, tb = (texture_statistics(image) for image in
                      (result_top, result_bottom, truth_top, truth_bottom))
    scale = float(np.std(truth))
    floor = group_distances(tt, tb, scale)
    one, two = group_distances(rt, tb, scale), group_distances(rb, tt, scale)
    ratios = [0.5 * (one[g] + two[g]) / max(floor[g], FLOOR) for g in floor]
    return float(np.sqrt(np.mean(np.square(ratios))))
