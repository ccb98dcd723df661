"""Would lambda chosen inside the sample be the right one for the target? (issue 57, a study)

``python -m benchmarks.lambda_cv stone:5,fabric:1 1,3,10``: for each ``material:seed``, the
enlargement bench's one-photo case (:func:`benchmarks.enlarge._material`: a 128^2 truth under
btf's shading, ``abtf:12,4``, its central 64^2 at rank 16, the top light's layer as the
photo) enlarged with ``btf enlarge --lambda`` at each multiple of its default; and the same
problem inside the sample, where the truth is known: the sample's central 32^2 enlarged to
the whole 64^2 sample under the same light, at the same multiples of that problem's default.
One JSON line a case: the gap share and error at full size, and the error inside the sample,
per multiple. If the multiple with the lowest error inside the sample is the best (or near
it) at full size, the constraint weight could be chosen per material from the measurement
alone. Not a ``btf bench`` suite: a study whose figures are in BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.enlarge import _material, material_seeds
from tasks.evaluation import gap_share


def _clean(folder: Path) -> None:
    """Everything but the truth (``M.zarr``) and the inner problem, for the next run."""
    for child in folder.iterdir():
        if child.name not in ("M.zarr", "cv"):
            shutil.rmtree(child) if child.is_dir() else child.unlink()


def _gap(row: dict) -> float:
    return gap_share(row["final"]["error"], row["lookup"]["error"], row["oracle"]["error"])


def _runs(name: str, args: argparse.Namespace, folder: Path, mults: list[float],
          generate) -> dict[float, dict]:
    """The top set's row at each multiple of lambda; the first (1) measures the default."""
    rows: dict[float, dict] = {}
    for mult in mults:
        if rows:
            _clean(folder)
            args.enlarge_options = f"--lambda {rows[mults[0]]['lambda'] * mult}"
        rows[mult] = _material(name, args, folder, None if rows else generate)["sets"]["top"]
    return rows


def case(name: str, seed: int, mults: list[float]) -> dict:
    """One material and seed: every multiple at full size and inside the sample."""
    tmp = Path(tempfile.mkdtemp(prefix="btf-lambda-cv-"))
    try:
        start = time.perf_counter()
        args = argparse.Namespace(size=128, rank=16, sets="top", baselines="lookup", seed=seed,
                                  enlarge_options="", sheet=None)
        full = _runs(name, args, tmp, mults, ())
        inner = tmp / "cv"
        inner.mkdir()
        shutil.copytree(tmp / "S.zarr", inner / "M.zarr")  # the sample, as the inner truth
        inside = _runs(name, argparse.Namespace(**{**vars(args), "size": 64,
                                                   "enlarge_options": ""}), inner, mults, None)
        chosen = min(mults, key=lambda m: inside[m]["final"]["error"])
        return {"case": f"{name}:{seed}", "lambda": full[mults[0]]["lambda"],
                "inner_lambda": inside[mults[0]]["lambda"],
                "full_gap": {m: round(_gap(full[m]), 3) for m in mults},
                "full_error": {m: round(full[m]["final"]["error"], 5) for m in mults},
                "full_wall": {m: round(full[m]["wall"], 2) for m in mults},
                "inside_error": {m: round(inside[m]["final"]["error"], 5) for m in mults},
                "inside_wall": {m: round(inside[m]["wall"], 2) for m in mults},
                "chosen": chosen, "chosen_gap": round(_gap(full[chosen]), 3),
                "seconds": round(time.perf_counter() - start, 1)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print(__doc__.split("\n\n")[1], file=sys.stderr)
        return 2
    mults = [float(m) for m in argv[1].split(",")]
    if mults[0] != 1.0:
        print("the first multiple must be 1 (the default, measured first)", file=sys.stderr)
        return 2
    for name, seed in material_seeds(argv[0]):
        print(json.dumps(case(name, seed, mults)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
