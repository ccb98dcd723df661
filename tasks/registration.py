"""Where a sample lies in larger images: normalised cross-correlation (FFT-based).

Used by BTF enlargement when the user does not give the sample's place in the constraint
photos: the sample's own rendering of the constraint layers is matched against the photos
(scikit-image's ``match_template``, the correlation coefficient of every placement, computed
with FFTs), over all constraint channels at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

AMBIGUITY = 1e-3  # correlations this close to the best are as good a match
MAX_ALIKE = 8  # such places listed


@dataclass(frozen=True)
class Match:
    """The best placement of a template: its top-left texel and correlation coefficient.

    ``runner_up`` is the best score at least a template's half-size away from it (-1 if there
    is no such placement): a periodic texture matches well in several places. ``alike``
    lists the places (y, x, score), each at least that far from the others, that match
    within :data:`AMBIGUITY` of the best (at most :data:`MAX_ALIKE`).
    """

    y: int
    x: int
    score: float
    runner_up: float
    alike: tuple[tuple[int, int, float], ...] = ()

    def ambiguous(self) -> bool:
        """Whether other places match as well as the best."""
        return bool(self.alike)


def locate(template: np.ndarray, image: np.ndarray) -> Match:
    """Best placement of ``template`` ``(h, w, c)`` in ``image`` ``(H, W, c)``."""
    from skimage.feature import match_template

    template = np.asarray(template, np.float64)
    image = np.asarray(image, np.float64)
    if template.shape[2:] != image.shape[2:] or any(
            t > i for t, i in zip(template.shape[:2], image.shape[:2], strict=True)):
        raise ValueError(f"a {template.shape} template does not fit in a {image.shape} image")
    score = match_template(image, template)
    score = score.reshape(score.shape[0], score.shape[1])
    score = np.where(np.isfinite(score), score, -1.0)  # flat windows have no correlation
    y, x = np.unravel_index(int(np.argmax(score)), score.shape)
    ry, rx = max(1, template.shape[0] // 2), max(1, template.shape[1] // 2)
    yy, xx = np.ogrid[: score.shape[0], : score.shape[1]]

    def away(cy, cx):
        return (np.abs(yy - cy) >= ry) | (np.abs(xx - cx) >= rx)

    free = away(y, x)
    runner_up = float(score[free].max()) if free.any() else -1.0
    alike = []
    while free.any() and len(alike) < MAX_ALIKE:
        masked = np.where(free, score, -np.inf)
        ay, ax = np.unravel_index(int(np.argmax(masked)), score.shape)
        if score[ay, ax] < score[y, x] - AMBIGUITY:
            break
        alike.append((int(ay), int(ax), float(score[ay, ax])))
        free &= away(ay, ax)
    return Match(int(y), int(x), float(score[y, x]), runner_up, tuple(alike))
