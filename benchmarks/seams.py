"""Seams of quilted textures made from photos: wrap seams, tile borders and blur.

A photo (scikit-image ships ``brick``, ``gravel`` and ``grass``; generated materials by name)
becomes a three-layer reference image through three tone curves (``g``, ``sqrt g``, ``g^2``),
as a user quilting a photo would. For each seed:

- **wrap** (one corner type): the mean absolute difference of the texel pairs that meet across
  the periodic texture's wrap (last column / first column, last row / first row), divided by the
  mean over all neighbour pairs inside the texture;
- **tile borders** (two corner types, 16 tiles): a 4 x 4 mosaic of corner-compatible tiles laid
  by random corner types; pairs across tile borders against all pairs inside the mosaic;
- **blur**: the texture's mean neighbour difference divided by the photo's (1 = as sharp).

A single line of texels carries a lot of chance on a structured texture (a wrap that runs along
a mortar line measures high without any defect), so the ratios are pooled over seeds: total
difference across seams over all seeds divided by the pooled interior mean; the per-seed range
is reported next to it.
"""

from __future__ import annotations

import numpy as np

PHOTOS = ("brick", "gravel", "grass")


def reference_of(name: str, size: int = 256) -> np.ndarray:
    """The three-tone-curve reference image of a photo or a generated material (size^2 crop)."""
    if name in PHOTOS:
        from skimage import data

        g = getattr(data, name)().astype(np.float32) / 255.0
        if g.ndim == 3:
            g = g[..., :3] @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    else:
        from tasks.materials import Material

        albedo = Material(name, seed=1).fields(0, 0, size, size).albedo
        g = (albedo @ np.array([0.2126, 0.7152, 0.0722])).astype(np.float32)
        g = (g - g.min()) / max(float(np.ptp(g)), 1e-6)
    g = g[:size, :size]
    return np.stack([g, np.sqrt(g), g * g], axis=-1)


def _pairs(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean absolute differences of horizontal and vertical neighbour pairs (per pair)."""
    return (np.abs(np.diff(img, axis=1)).mean(axis=-1), np.abs(np.diff(img, axis=0)).mean(axis=-1))


def wrap_seam(tile: np.ndarray) -> tuple[float, float, int]:
    """Sum of differences across the wrap, the interior mean, and the number of wrap pairs."""
    dx, dy = _pairs(tile)
    across = np.abs(tile[:, -1] - tile[:, 0]).mean(-1).sum() + np.abs(
        tile[-1] - tile[0]).mean(-1).sum()
    interior = (dx.sum() + dy.sum()) / (dx.size + dy.size)
    return float(across), float(interior), tile.shape[0] + tile.shape[1]


def mosaic_seams(tiles: list[np.ndarray], corners: np.ndarray, types: int, count: int,
                 rng: np.random.Generator) -> tuple[float, float, int]:
    """A ``count x count`` mosaic of corner-compatible tiles: sum across borders, interior mean,
    border pairs."""
    th, tw = tiles[0].shape[:2]
    lookup = {tuple(c): k for k, c in enumerate(corners.tolist())}
    grid = rng.integers(types, size=(count + 1, count + 1))
    rows = []
    for i in range(count):
        row = [tiles[lookup[(grid[i, j], grid[i, j + 1], grid[i + 1, j], grid[i + 1, j + 1])]]
               for j in range(count)]
        rows.append(np.concatenate(row, axis=1))
    image = np.concatenate(rows, axis=0)
    dx, dy = _pairs(image)
    bx = np.zeros(dx.shape, bool)
    bx[:, tw - 1 :: tw] = True
    by = np.zeros(dy.shape, bool)
    by[th - 1 :: th] = True
    across = dx[bx].sum() + dy[by].sum()
    interior = (dx[~bx].sum() + dy[~by].sum()) / ((~bx).sum() + (~by).sum())
    return float(across), float(interior), int(bx.sum() + by.sum())


def neighbour_difference(img: np.ndarray) -> float:
    dx, dy = _pairs(img)
    return float((dx.sum() + dy.sum()) / (dx.size + dy.size))


def texture_seams(name: str, *, block: int | None, overlap: int | None, seeds: int,
                  candidates: int = 5, tile_steps: int = 7, mosaic_seeds: int = 2) -> dict:
    """Pooled wrap and tile-border seam ratios and blur of one texture (see module)."""
    import time

    from tasks.quilting import QuiltParams, choose_block, plan_tiles

    reference = reference_of(name, 512 if name in PHOTOS else 256)
    why = "given"
    if block is None:
        block, auto_overlap, why = choose_block(reference)
        overlap = auto_overlap if overlap is None else overlap
    overlap = max(2, block // 4) if overlap is None else overlap
    step = block - overlap
    size = max(2, tile_steps) * step
    own = neighbour_difference(reference)
    wraps, per_seed, sharpness, seconds = [], [], [], 0.0
    for seed in range(seeds):
        start = time.perf_counter()
        plan = plan_tiles(reference, QuiltParams(block, overlap, candidates, 1, (size, size)),
                          seed=seed)
        seconds += time.perf_counter() - start
        tile = plan.tiles[0].value
        across, interior, n = wrap_seam(tile)
        wraps.append((across, interior, n))
        per_seed.append(across / n / interior)
        sharpness.append(interior / own)
    wrap = sum(a for a, _, _ in wraps) / sum(n for _, _, n in wraps) / np.mean(
        [i for _, i, _ in wraps])
    borders, border_seeds = [], []
    mosaic_size = max(2, tile_steps // 2) * step
    for seed in range(mosaic_seeds):
        plan = plan_tiles(reference, QuiltParams(block, overlap, candidates, 2,
                                                 (mosaic_size, mosaic_size)), seed=seed)
        across, interior, n = mosaic_seams([t.value for t in plan.tiles], plan.corners, 2, 4,
                                           np.random.default_rng(seed))
        borders.append((across, interior, n))
        border_seeds.append(across / n / interior)
    border = (sum(a for a, _, _ in borders) / sum(n for _, _, n in borders)
              / np.mean([i for _, i, _ in borders])) if borders else float("nan")
    return {"texture": name, "block": block, "overlap": overlap, "why": why, "tile": size,
            "seeds": seeds, "wrap": float(wrap), "wrap_range": [min(per_seed), max(per_seed)],
            "border": float(border), "border_range": ([min(border_seeds), max(border_seeds)]
                                                      if border_seeds else None),
            "sharpness": float(np.mean(sharpness)),
            "sharpness_range": [min(sharpness), max(sharpness)],
            "plan_seconds": seconds / max(seeds, 1)}


def seams_report(rows: list[dict]) -> list[str]:
    """Markdown table of :func:`texture_seams` rows."""
    lines = ["| texture | block / overlap | tile | wrap seam (pooled; per seed) | tile borders, "
             "V = 2 (pooled; per seed) | sharpness vs photo (mean; range) | plan s |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        br = r["border_range"]
        lines.append(
            f"| {r['texture']} | {r['block']} / {r['overlap']} ({r['why']}) | {r['tile']}^2 | "
            f"{r['wrap']:.2f} ({r['wrap_range'][0]:.2f}-{r['wrap_range'][1]:.2f}) | "
            + (f"{r['border']:.2f} ({br[0]:.2f}-{br[1]:.2f})" if br else "-")
            + f" | {r['sharpness']:.2f} ({r['sharpness_range'][0]:.2f}-"
              f"{r['sharpness_range'][1]:.2f}) | {r['plan_seconds']:.1f} |")
    return lines
