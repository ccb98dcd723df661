"""btf-extractor 1.7.0 (PyPI) as an independent DFMF reader, run in its own venv.

It needs Cython < 3 and numpy < 2 and compiles C++ (``-Ofast -march=native -fopenmp``), so it
lives in ``.venv-btfx`` (installed by ``.ci/run``, see there) and is called via subprocess.

What its source says (``btf_extractor/ubo2014.pyx`` and the bundled ``c_ext/btf.hh``, Zdravko
Velinov's "Free BTF Library"), checked against files from ``tests/dfmf_files.py``:

- **Angles**: ``Ubo2014(path).angles_to_image(tl, pl, tv, pv)`` takes *degrees*, light first,
  and looks the tuple up in a dict by exact float equality. Keys are made by converting each
  stored (theta, phi) to a float32 unit vector (tan half-angle sin/cos), then back:
  ``theta = deg(arccos z)``, ``phi = deg(arctan2(y, x)) % 360`` (so phi is in [0, 360), file
  phi in (-180, 180] is wrapped), both rounded to 0.1 deg in float32 and turned into Python
  floats (exact for multiples of 0.5 deg; 37.3 becomes 37.29999923706055). A phi just under
  360 rounds to 360.0. At theta = 0 the phi key is 0.0 or 180.0 (sign of a zero x), whatever
  was stored. ``btfx_images`` therefore matches each requested tuple to the nearest key (phi
  circular, phi ignored at theta 0) and refuses deviations over 0.06 deg.
- **Sampling**: only the first view's light list is read; later lists must have the same
  *count* (their angles are skipped, not compared). Rows must be ``nL * nL``: nV != nL fails.
- **Indices**: row ``view * nL + light`` (light fastest), texel ``y * W + x``: as the format.
- **Rows flipped**: after loading it swaps S x V rows so that image row ``y`` is the file's
  texel row ``H - 1 - y``: the file's rows run from the bottom of the picture. btf reads them
  the same way, so its layers and these images agree row for row.
- **Channel order**: BGR (``img[..., 0]`` is the file's third channel).
- **Colour models**: 0 and 11 only. Model 0: the channel sums as they are, **not clamped**.
  Model 11: ``Y = exp(c0) - 1e-5``, ``U = c1 * Y + 1e-5``, ``V = c2 * Y + 1e-5`` (btflib:
  ``c1 * (Y + eps)``), YUV -> RGB with the usual matrix, then clamped to [0, 1]. Any other
  model: an ``assert`` compiled out by ``-DNDEBUG``, so the raw channel sums come back
  silently, untransformed. Colour mean and matrix are read and ignored.
- **Cosine flag**: read, then a compiled-out ``assert(false && "Stub")``: no division.
- **Channels**: 3 expected; any other count gives zeros (compiled-out asserts).
- **Scalars**: float16 (F16C, float32 sums), float32, float64 (double sums, cast to float32);
  all channels must share one scalar size. Metadata size must match exactly and the file must
  end right after the last S x V.
- **Dtype/shape**: ``np.float32`` (height, width, 3), C-contiguous. (``img_shape`` says
  (width, height, 3): swapped for non-square images; the arrays are right.)
- **Errors**: ``LoadBTF`` returns NULL on any bad file and the Cython wrapper then reads
  ``NULL->Width``: the process dies with SIGSEGV. Paths must be ``str``.
- **Threads**: each image is decoded with an OpenMP ``prange`` over rows (``OMP_NUM_THREADS``).
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BTFX_PYTHON = ROOT / ".venv-btfx" / "bin" / "python"

_SCRIPT = r"""
import json, sys, time
import numpy as np
from btf_extractor import Ubo2014

path, pairs_file, out_file, repeat = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
pairs = np.load(pairs_file)
btf = Ubo2014(path)
keys = sorted(btf.angles_set)
karr = np.array(keys, dtype=np.float64)

def key_for(p):
    d_t = np.abs(karr[:, [0, 2]] - p[[0, 2]])
    d_p = np.abs((karr[:, [1, 3]] - p[[1, 3]] + 180.0) % 360.0 - 180.0)
    d_p[karr[:, [0, 2]] < 0.05] = 0.0  # phi means nothing at theta 0
    dev = np.maximum(d_t, d_p).max(axis=1)
    i = int(np.argmin(dev))
    if dev[i] > 0.06:
        sys.exit(f"no direction pair near {tuple(p)} in {path}; it has {keys}")
    return keys[i]

chosen = [key_for(p) for p in pairs]
if repeat == 0:
    np.save(out_file, np.stack([btf.angles_to_image(*k) for k in chosen]).astype(np.float32))
else:
    btf.angles_to_image(*chosen[0])  # warm up (OpenMP thread pool, page cache)
    t0 = time.perf_counter()
    for _ in range(repeat):
        for k in chosen:
            btf.angles_to_image(*k)
    dt = (time.perf_counter() - t0) / (repeat * len(chosen))
    with open(out_file, "w") as f:
        json.dump({"seconds_per_image": dt}, f)
"""


@functools.cache
def btfx_available() -> bool:
    """Whether ``.venv-btfx/bin/python`` exists and imports ``btf_extractor``."""
    if not BTFX_PYTHON.exists():
        return False
    r = subprocess.run([str(BTFX_PYTHON), "-c", "import btf_extractor"],
                       capture_output=True, timeout=120, check=False)
    return r.returncode == 0


def _run(path, pairs, repeat: int, out_name: str, threads: int | None):
    pairs = np.asarray(pairs, dtype=np.float64).reshape(-1, 4)
    env = dict(os.environ)
    if threads is not None:
        env["OMP_NUM_THREADS"] = str(threads)
    with tempfile.TemporaryDirectory(prefix="btfx-") as tmp:
        pairs_file, out_file = Path(tmp) / "pairs.npy", Path(tmp) / out_name
        np.save(pairs_file, pairs)
        r = subprocess.run([str(BTFX_PYTHON), "-c", _SCRIPT, str(Path(path).resolve()),
                            str(pairs_file), str(out_file), str(repeat)],
                           capture_output=True, text=True, env=env, timeout=600, check=False)
        if r.returncode != 0:
            why = " (SIGSEGV: btf-extractor's LoadBTF refused the file)" \
                if r.returncode == -11 else ""
            raise RuntimeError(f"btf-extractor failed on {path}, exit {r.returncode}{why}:\n"
                               f"{r.stderr.strip()[-2000:]}")
        if repeat == 0:
            return np.load(out_file)
        return json.loads(out_file.read_text())["seconds_per_image"]


def btfx_images(path, pairs, *, threads: int | None = None) -> np.ndarray:
    """btf-extractor's images of ``path`` for (theta_l, phi_l, theta_v, phi_v) in degrees.

    Returns float32 (len(pairs), height, width, 3) exactly as ``angles_to_image`` gives them:
    rows flipped, BGR, model 11 clamped to [0, 1], model 0 unclamped (see the module doc).
    Each tuple is matched to the nearest stored key (phi in any range, at most 0.06 deg off).
    ``as_store_layers`` turns them into a store's layers (the channel order).
    """
    return _run(path, pairs, 0, "images.npy", threads)


def btfx_time(path, pairs, *, repeat: int = 3, threads: int | None = None) -> float:
    """Seconds per ``angles_to_image`` call, timed inside the subprocess.

    Excludes interpreter start, imports, opening (loading) the file and a warm-up call; the
    mean over ``repeat`` passes over ``pairs``. ``threads`` sets ``OMP_NUM_THREADS``.
    """
    return _run(path, pairs, max(1, repeat), "time.json", threads)


def as_store_layers(images: np.ndarray) -> np.ndarray:
    """btf-extractor images (..., height, width, BGR) as a store's layers (RGB).

    Its rows are already the store's: it reverses the file's texel rows, as btf's reader does
    (docs/formats.md, "The frame"), so only the channel order changes.
    """
    return images[..., ::-1]
