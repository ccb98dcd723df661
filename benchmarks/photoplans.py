"""Quilt plans on photos for seeds and crops drawn at random: what a user's ``btf quilt`` costs.

The issue behind it (56, part 3): ``btf quilt --corners 2`` on a 256^2 crop of a photo took
up to 39-92 s to plan on seeds outside the seams bench's fixed range. Here every run draws
its own crops and seeds, so no planner change can be tuned to a fixed few:

- **Photos**: scikit-image's ``brick``, ``gravel`` and ``grass`` (they ship with the package).
  Each draw takes a 256^2 crop at a random place and makes the three-light BTF a user would
  ingest from it (the photo ``g``, ``sqrt g`` and ``g^2`` lit from the top and from 30 degrees
  at azimuths 0 and 90); the reference image is the one ``btf quilt`` plans on for such a
  store (:func:`tasks.reference.reference_maps` of its light sums, the default weights).
- **Plans**: ``btf quilt``'s defaults: the automatic block (and the larger ones after it),
  tiles of the sample's size rounded down to whole steps, V = 2 (16 tiles), K = 5, the border
  check's bound 1.3, tiles planned on every core (:func:`tasks.corner_tiles.plan_first`).
- **Figures** per draw: the planning time, the tile interiors planned, the block that passed,
  or the refusal; the seam and structure ratios of a 4 x 4 mosaic of the tiles
  (:func:`benchmarks.seams.seed_figures`, each tile framed by its neighbours) and the
  sharpness.
- **Floor**, measured in the same run: the first draw of each photo planned with the check's
  bound lifted, i.e. every tile planned once: what planning costs when no plan is made again.

The draw is printed; ``--photo-draw N`` repeats it.
"""

from __future__ import annotations

import sys

import numpy as np

from benchmarks.seams import photo

PHOTOS = ("brick", "gravel", "grass")
SIZE = 256
# the three lights of the BTF made from a photo: (theta, phi) in degrees, and its tone curve
LIGHTS = ((0.0, 0.0, lambda g: g), (30.0, 0.0, np.sqrt), (30.0, 90.0, np.square))


def photo_reference(g: np.ndarray) -> np.ndarray:
    """The reference image ``btf quilt`` plans on for the three-light BTF of a photo crop."""
    from tasks.reference import light_sums, reference_maps
    from tasks.sampling import direction_vectors

    rgb = np.repeat(g[..., None], 3, axis=-1)
    layers = np.stack([curve(rgb) for _, _, curve in LIGHTS]).astype(np.float32)
    lights = direction_vectors(np.array([t for t, _, _ in LIGHTS]),
                               np.array([p for _, p, _ in LIGHTS]))
    return reference_maps(light_sums(layers, lights)).reference


def draws(draw: int, names, count: int) -> list[dict]:
    """``count`` crops and seeds per photo, from the generator of ``draw``."""
    rng = np.random.default_rng(draw)
    out = []
    for name in names:
        h, w = photo(name).shape
        for _ in range(count):
            out.append({"photo": name, "crop": [int(rng.integers(0, h - SIZE + 1)),
                                                int(rng.integers(0, w - SIZE + 1))],
                        "seed": int(rng.integers(0, 2**31))})
    return out


def measure(case: dict, *, threads: int, max_seam: float = 1.3) -> dict:
    """One draw planned as ``btf quilt --corners 2`` plans it, and measured (see the module)."""
    from benchmarks.seams import seed_figures
    from tasks.quilt_layout import sample_lattice

    y, x = case["crop"]
    g = photo(case["photo"])[y : y + SIZE, x : x + SIZE]
    reference = photo_reference(g)
    lattice = sample_lattice(reference)
    row = seed_figures(case["photo"], reference, lattice, block=None, overlap=None, corners=2,
                       seed=case["seed"], threads=threads, default_tiles=True,
                       max_seam=max_seam)
    return {**case, **row}


def run(names, count: int, draw: int | None, threads: int, log=None) -> dict:
    """Every draw of every photo, and each photo's floor (see the module)."""
    from benchmarks.seams import summary

    if draw is None:
        draw = int(np.random.SeedSequence().entropy % 2**32)
    say = log or (lambda line: print(line, file=sys.stderr))
    say(f"photo plans: draw {draw} (--photo-draw {draw} repeats it)")
    rows, floors = [], {}
    for case in draws(draw, names, count):
        row = measure(case, threads=threads)
        rows.append(row)
        say(f"photo plans: {row['photo']} crop {tuple(row['crop'])} seed {row['seed']}: "
            + (f"REFUSED {row['failed']}" if row["failed"] else
               f"{row['seconds']:.1f} s, block {row['block']}, {row['interior_plans']} "
               f"interior plans, seam {row['seam']:.2f}, structure {row['structure']:.2f}"))
        if row["photo"] not in floors:
            once = measure(case, threads=threads, max_seam=1e9)
            floors[row["photo"]] = {"seconds": once["seconds"], "block": once["block"]}
    by_photo = []
    for name in names:
        mine = [r for r in rows if r["photo"] == name]
        by_photo.append({"photo": name, "draws": len(mine), "floor": floors[name],
                         **summary(mine, keys=("seconds", "seam", "structure", "sharpness",
                                               "interior_plans"))})
    return {"draw": draw, "threads": threads, "rows": rows, "photos": by_photo}


def report(result: dict) -> list[str]:
    """Markdown table of :func:`run`'s result."""
    def fig(s, key, fmt):
        v = s[key]
        return "-" if v is None else f"{v['worst']:{fmt}} / {v['median']:{fmt}}"

    lines = [f"Quilt plans on photos (`benchmarks/photoplans.py`), draw {result['draw']}: "
             "256^2 crops at random places and random seeds, `btf quilt --corners 2`'s "
             f"defaults (16 tiles of the sample's size), {result['threads']} planning "
             "threads. Floor: the first draw of each photo with every tile planned once (the "
             "check's bound lifted), in the same run.", "",
             "| photo | draws | refused | plan s: worst / median | floor s | interior plans: "
             "worst / median | seam: worst / median | structure: worst / median | "
             "sharpness: lowest / median |", "|---|---|---|---|---|---|---|---|---|"]
    for s in result["photos"]:
        lines.append(f"| {s['photo']} | {s['draws']} | {len(s['failed'])} | "
                     f"{fig(s, 'seconds', '.1f')} | {s['floor']['seconds']:.1f} | "
                     f"{fig(s, 'interior_plans', '.0f')} | {fig(s, 'seam', '.2f')} | "
                     f"{fig(s, 'structure', '.2f')} | {fig(s, 'sharpness', '.2f')} |")
    every = [r["seconds"] for r in result["rows"] if not r["failed"]]
    if every:
        lines += ["", f"All photos: worst {max(every):.1f} s, median {np.median(every):.1f} s "
                      f"over {len(every)} plans (goal: worst <= 5 s, median <= 2 s)."]
    return lines
