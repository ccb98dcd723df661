"""Numerical stress: every stage on inputs at the edges of what a user may feed it.

Each case is a radiance store that went through the user's path: a generated store exported to
EXR files, the files' pixels replaced by the case (HDR extremes from 1e-6 to 1e6, constant and
all-zero layers, single-texel spikes, half floats), then ingested; plus a single light, an odd
non-square crop and a crop smaller than a quilting block; ``btf generate`` also gets each value
case as the photo of ``--albedo``. Every stage then runs on it with small
settings. A stage passes when it exits 0 with finite output (and, where the answer is known,
the right one), or exits 1 with one clear error line and nothing written at OUT. A crash, a
NaN, a traceback or a run over the time limit fails.

``BTF_STRESS_REPORT=FILE pytest -m stress`` also writes the stage x case matrix to FILE.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import signal
from pathlib import Path

import numpy as np
import pytest
import zarr

from helpers import generate_store, no_partial_outputs
from pipeline.images import read_image, write_exr
from pipeline.stores.base import RADIANCE

pytestmark = pytest.mark.stress

TIME_LIMIT = 180  # seconds per stage run
CASES = ("hdr", "constant", "zero", "spike", "half", "single-light", "odd", "small")
REPORTED = (*CASES, "half-overflow", "nan")
STAGES = ("generate", "ingest", "compress", "reconstruct", "quilt", "roller", "fit", "render",
          "enlarge")
MATRIX: dict[tuple[str, str], str] = {}


def _pixels(case: str, pixels: np.ndarray, layer: int) -> np.ndarray:
    rng = np.random.default_rng(layer)
    if case == "hdr":
        return 10.0 ** rng.uniform(-6.0, 6.0, pixels.shape)
    if case == "constant":
        return np.full_like(pixels, 0.5)
    if case == "zero":
        return np.zeros_like(pixels)
    if case == "spike":
        out = np.full_like(pixels, 0.01)
        out[pixels.shape[0] // 3, pixels.shape[1] // 2] = 1e6
        return out
    return pixels


@pytest.fixture(scope="module", autouse=True)
def matrix_report():
    """Writes the stage x case matrix when the module's tests are done and
    ``BTF_STRESS_REPORT`` is set (whatever order the tests ran in)."""
    yield
    target = os.environ.get("BTF_STRESS_REPORT")
    if not target:
        return
    lines = ["| stage | " + " | ".join(REPORTED) + " |", "|---" * (len(REPORTED) + 1) + "|"]
    for stage in STAGES:
        lines.append(f"| {stage} | " + " | ".join(
            MATRIX.get((stage, case), "-").replace("|", "/") for case in REPORTED) + " |")
    Path(target).write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    """``{case: (radiance store, generate/ingest outcome)}``; see the module."""
    tmp = tmp_path_factory.mktemp("stress")
    from pipeline.cli import main

    def btf(*args) -> tuple[int, str]:
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            code = main([str(a) for a in args] + ["--quiet"])
        return code, err.getvalue()

    base = generate_store(tmp / "base.zarr", "--material", "tiles", "--size", "48", "--sampling",
                          "abtf:4,2", "--scale", "16", "--chunk", "16", "--seed", "2")
    out = {}
    for case in ("hdr", "constant", "zero", "spike", "half"):
        folder = tmp / f"{case}-exr"
        assert btf("export", base, folder)[0] == 0
        for k, path in enumerate(sorted(folder.glob("*.exr"))):
            pixels, channels = read_image(path)
            write_exr(path, _pixels(case, pixels, k), channels, half=case == "half")
        out[case] = tmp / f"{case}.zarr"
        MATRIX[("ingest", case)] = _outcome(*btf("ingest", folder, out[case], "--chunk", "16"),
                                            out=out[case])
    for case in ("hdr", "constant", "zero", "spike"):  # the case as a photo to generate from
        photo = tmp / f"{case}-photo.exr"
        write_exr(photo, _pixels(case, np.zeros((40, 56, 3), np.float32), 0), ("R", "G", "B"))
        target = tmp / f"{case}-generated.zarr"
        MATRIX[("generate", case)] = _outcome(*btf("generate", target, "--albedo", photo,
                                                   "--sampling", "abtf:4,2"), out=target)
    out["single-light"] = tmp / "single.zarr"
    MATRIX[("generate", "single-light")] = _outcome(*btf(
        "generate", out["single-light"], "--material", "leather", "--size", "33", "--sampling",
        "abtf:1,1", "--chunk", "16"), out=out["single-light"])
    out["odd"] = tmp / "odd.zarr"
    generate_store(tmp / "odd-base.zarr", "--material", "fabric", "--size", "61", "--sampling",
                   "abtf:4,2", "--chunk", "16")
    assert btf("crop", tmp / "odd-base.zarr", out["odd"], "--region", "3:40,0:61")[0] == 0
    MATRIX[("generate", "odd")] = "ok: 61 x 61, cropped to 37 x 61"
    out["small"] = tmp / "small.zarr"
    assert btf("crop", base, out["small"], "--region", "0:12,0:12")[0] == 0
    return out


def _finite(path: Path) -> bool:
    if path.suffix == ".exr":
        return bool(np.isfinite(read_image(path)[0]).all())
    group = zarr.open_group(path, mode="r")
    for _, array in group.arrays():
        if array.dtype.kind == "f" and not np.isfinite(array[...]).all():
            return False
    return True


def _outcome(code: int, err: str, out: Path) -> str:
    if code == 0:
        assert _finite(out), f"{out}: NaN or infinity in the output"
        return "ok"
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert code == 1, err
    assert "Traceback" not in err, err
    assert len(lines) == 1 and "error:" in lines[0], err
    assert no_partial_outputs(out), f"{out} was left behind"
    return "error: " + re.sub(r"/\S*/", "", lines[0].split("error:", 1)[1].strip())


class _TimeLimit(Exception):
    pass


def _alarm(signum, frame):
    raise _TimeLimit(f"over {TIME_LIMIT} s")


def run_stage(btf, stage: str, case: str, out: Path, *args) -> str:
    """Run ``btf stage args... out``-style command; record and return its outcome."""
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(TIME_LIMIT)
    try:
        result = btf(*args, "--quiet")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    outcome = _outcome(result.code, result.err, out)
    MATRIX[(stage, case)] = outcome
    return outcome


def _values(path: Path) -> np.ndarray:
    return zarr.open_group(path, mode="r")[RADIANCE][...]


@pytest.mark.parametrize("case", CASES)
def test_compress_and_reconstruct(btf, cases, case, tmp_path):
    store = cases[case]
    want = _values(store)
    rows = want.shape[0] * want.shape[1] * want.shape[-1]
    svd = tmp_path / "svd.zarr"
    assert run_stage(btf, "compress", case, svd, "compress", store, svd, "--rank", rows) == "ok"
    out = tmp_path / "rec.zarr"
    assert run_stage(btf, "reconstruct", case, out, "reconstruct", svd, out) == "ok"
    # at full rank the factorisation is exact up to float32 arithmetic in the log domain,
    # log(x + eps) (eps = 1e-3): the fused power passes work on A^T A in float32, so the
    # smallest components of an ill-conditioned matrix carry that rounding (the odd fabric crop:
    # singular values 645 to 4.8e-4, one value of 54168 off by 1.08e-3; the next 8.4e-4)
    got = _values(out)
    np.testing.assert_allclose(np.log(got + 1e-3), np.log(want + 1e-3), atol=2e-3, rtol=0)
    big = want > 1e-2  # and relative in linear radiance where eps does not dominate
    np.testing.assert_allclose(got[big], want[big], rtol=3e-3)
    if np.ptp(want) > 0:  # the check would catch a wrong reconstruction
        with pytest.raises(AssertionError):
            np.testing.assert_allclose(np.log(np.roll(got, 1) + 1e-3), np.log(want + 1e-3),
                                       atol=1e-3, rtol=0)


@pytest.mark.parametrize("case", CASES)
def test_quilt_and_render(btf, cases, case, tmp_path):
    quilt = tmp_path / "q.zarr"
    outcome = run_stage(btf, "quilt", case, quilt, "quilt", cases[case], quilt, "--block", "16",
                        "--overlap", "4", "--size", "36,36")
    if case == "small":
        assert "block" in outcome  # 12 x 12 is smaller than a 16 x 16 block
        return
    assert outcome == "ok"
    exr = tmp_path / "surface.exr"
    assert run_stage(btf, "render", case, exr, "render", quilt, exr, "--light", "0",
                     "--size", "50,70") == "ok"
    if case in ("constant", "zero"):  # blending weights sum to 1 up to float32 rounding
        np.testing.assert_allclose(read_image(exr)[0], _values(cases[case]).flat[0], rtol=1e-6,
                                   atol=1e-30)


@pytest.mark.parametrize("case", CASES)
def test_roller(btf, cases, case, tmp_path):
    out = tmp_path / "r.zarr"
    outcome = run_stage(btf, "roller", case, out, "roller", cases[case], out)
    if case in ("constant", "zero", "hdr", "spike", "single-light"):  # nothing periodic left
        assert "no clear periodicity" in outcome
    elif case == "half":  # the generated tiles, through half floats: still a lattice
        assert outcome == "ok"
    elif case == "odd":  # 37 x 61 texels of fabric: a period, but no room to cut around it
        assert "too small for one period" in outcome
    else:  # 12 x 12 texels
        assert case == "small" and "at least 16 x 16" in outcome


@pytest.mark.parametrize("case", CASES)
def test_fit(btf, cases, case, tmp_path):
    from pipeline.stores.fitted import open_fitted

    out = tmp_path / "f.zarr"
    assert run_stage(btf, "fit", case, out, "fit", cases[case], out) == "ok"
    fitted = open_fitted(out)
    want = _values(cases[case])
    rebuilt = fitted[RADIANCE].values
    error = fitted.attrs["fit_error"]
    # the reported error is the rebuilt store's
    assert np.sqrt(np.mean((rebuilt - want) ** 2)) == pytest.approx(error["rmse"], rel=1e-3,
                                                                   abs=1e-30)
    if case in ("constant", "zero"):  # one value everywhere: six parameters give it exactly
        np.testing.assert_allclose(rebuilt, want, rtol=1e-5, atol=1e-30)


@pytest.mark.parametrize("case", CASES)
def test_enlarge(btf, cases, case, tmp_path):
    store = cases[case]
    shape = zarr.open_group(store, mode="r")[RADIANCE].shape
    h, w = shape[2], shape[3]
    sample, sample_svd, photos = (tmp_path / n for n in ("s.zarr", "s_svd.zarr", "c.zarr"))
    y0, x0 = h // 4, w // 4
    assert btf("crop", store, sample, "--region", f"{y0}:{y0 + h // 2},{x0}:{x0 + w // 2}",
               "--quiet").code == 0
    rank = min(4, 3 * zarr.open_group(store, mode="r")[RADIANCE].shape[1])
    assert btf("compress", sample, sample_svd, "--rank", rank, "--quiet").code == 0
    assert btf("crop", store, photos, "--light", "0", "--quiet").code == 0
    out = tmp_path / "e.zarr"
    outcome = run_stage(btf, "enlarge", case, out, "enlarge", sample_svd, photos, out,
                        "--sample-origin", f"{y0},{x0}", "--levels", "2", "--iterations", "2",
                        "--rounds", "1")
    if case == "small":  # a 6 x 6 sample is 3 x 3 at the coarser level: below --patch 4
        assert "smaller than a neighbourhood" in outcome
    else:
        assert outcome == "ok"


@pytest.mark.parametrize("case", ["half-overflow", "nan"])
def test_ingest_refuses_files_that_are_not_finite(btf, cases, case, tmp_path):
    """1e6 does not fit a half float (it becomes infinity); a NaN texel is not a radiance."""
    folder = tmp_path / "exr"
    assert btf("export", cases["hdr"], folder, "--quiet").code == 0
    first = sorted(folder.glob("*.exr"))[2]
    pixels, channels = read_image(first)
    if case == "nan":
        pixels[5, 7, 1] = np.nan
    with np.errstate(over="ignore"):  # the overflow to infinity is the point of the case
        write_exr(first, pixels, channels, half=case == "half-overflow")
    out = tmp_path / "in.zarr"
    outcome = run_stage(btf, "ingest", case, out, "ingest", folder, out)
    assert outcome.startswith("error:") and first.name in outcome
