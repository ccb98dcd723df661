"""Archive ingest against the JPEG decoder alone (issue 32, part 5).

Writes a synthetic UBO2003-style zip (the 81-direction hemisphere, a folder per view, index
prefixes, JPEGs of ``size``^2), then in the same run measures the plain JPEG decode rate of its
members (imagecodecs' libjpeg-turbo, bytes already in memory: one thread, and two threads) and
the rate of ``btf ingest`` on the archive (reading the zip, decoding, sRGB to linear, staging
and the aligned copy into the store). Rates are images per second.

Run: ``python -c "from benchmarks.archives import archive_rates;
print(archive_rates('/tmp/a', views=9, lights=81))"``.
"""

from __future__ import annotations

import io
import shutil
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks.harness import btf_executable, machine, measure

# The Bonn/UTIA hemisphere: theta (degrees) and how many directions on its ring.
RINGS = ((0, 1), (15, 6), (30, 12), (45, 18), (60, 20), (75, 24))
PICTURES = 16  # distinct JPEGs; members cycle through them (decoding cost is the same)


def hemisphere(count: int = 81) -> list[tuple[int, int]]:
    """The first ``count`` of the 81 (theta, phi) directions, whole degrees, ring by ring."""
    out = [(theta, round(360 * k / n)) for theta, n in RINGS for k in range(n)]
    if not 1 <= count <= len(out):
        raise ValueError(f"between 1 and {len(out)} directions, not {count}")
    return out[:count]


def _pictures(size: int, quality: int) -> list[bytes]:
    """JPEGs of a textured picture (smooth structure plus grain), as cameras' photos are."""
    from PIL import Image

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:size, 0:size] / size
    out = []
    for k in range(PICTURES):
        base = 0.5 + 0.25 * np.sin(2 * np.pi * (3 + k) * x) * np.cos(2 * np.pi * 5 * y)
        rgb = np.stack([base, base ** 1.5, 1 - 0.5 * base], -1)
        rgb = rgb + rng.normal(0, 0.04, rgb.shape)
        pixels = (rgb.clip(0, 1) * 255).astype(np.uint8)
        buffer = io.BytesIO()
        Image.fromarray(pixels).save(buffer, "JPEG", quality=quality)
        out.append(buffer.getvalue())
    return out


def write_archive(path: Path, *, size: int, views: int, lights: int,
                  quality: int = 90) -> Path:
    """A UBO2003-style zip: ``UBO2003/MANYFILES/tv030_pv030/00008 tl000 pl000 tv030 pv030.jpg``."""
    pictures = _pictures(size, quality)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        index = 0
        for tv, pv in hemisphere(views):
            for tl, pl in hemisphere(lights):
                name = (f"UBO2003/MANYFILES/tv{tv:03d}_pv{pv:03d}/{index:05d} "
                        f"tl{tl:03d} pl{pl:03d} tv{tv:03d} pv{pv:03d}.jpg")
                z.writestr(name, pictures[index % PICTURES])
                index += 1
    return path


def decode_rate(members: list[bytes], threads: int) -> float:
    """Images per second of ``imagecodecs.jpeg8_decode`` on ``members`` (bytes in memory)."""
    import imagecodecs

    imagecodecs.jpeg8_decode(members[0])  # load the codec before timing
    start = time.perf_counter()
    if threads == 1:
        for data in members:
            imagecodecs.jpeg8_decode(data)
    else:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(imagecodecs.jpeg8_decode, members))
    return len(members) / (time.perf_counter() - start)


def archive_rates(workdir, *, size: int = 256, views: int = 81, lights: int = 81,
                  scheduler: str = "threads", sample: int = 2000, memory: bool = True) -> dict:
    """Decode and ingest rates (images/s) on a synthetic ``views`` x ``lights`` UBO2003 zip.

    ``decode_1``/``decode_2``: imagecodecs' JPEG decoder on ``sample`` members in memory, on one
    and two threads. ``ingest``: ``btf ingest`` in this process on ``scheduler``, after a
    one-image ingest has paid for the imports (its wall time includes scanning the zip, hashing
    it for provenance, decoding, sRGB to linear, checks, and writing the store).
    With ``memory``, the ingest runs again as its own process for its peak resident memory.
    """
    from pipeline.cli import main

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    archive = write_archive(workdir / f"ubo_{views}x{lights}_{size}.zip", size=size,
                            views=views, lights=lights)
    with zipfile.ZipFile(archive) as z:
        names = [i.filename for i in z.infolist()][:sample]
        members = [z.read(n) for n in names]
    images = views * lights
    out = workdir / "ingested.zarr"
    shutil.rmtree(out, ignore_errors=True)
    warm = write_archive(workdir / "warm.zip", size=size, views=1, lights=1)
    if main(["ingest", str(warm), str(out), "--quiet"]) != 0:  # imports, not timed
        raise RuntimeError("btf ingest failed on a one-image archive")
    shutil.rmtree(out)
    start = time.perf_counter()
    code = main(["ingest", str(archive), str(out), "--scheduler", scheduler, "--quiet"])
    seconds = time.perf_counter() - start
    if code != 0:
        raise RuntimeError(f"btf ingest failed with status {code}")
    result = {"images": images, "size": size, "archive_mb": round(archive.stat().st_size / 1e6, 1),
              "decode_1_per_s": round(decode_rate(members, 1)),
              "decode_2_per_s": round(decode_rate(members, 2)),
              "ingest_per_s": round(images / seconds), "ingest_s": round(seconds, 2),
              "scheduler": scheduler, "machine": machine()}
    if memory:
        shutil.rmtree(out)
        run = measure([btf_executable(), "ingest", str(archive), str(out), "--scheduler",
                       scheduler, "--quiet"])
        result["process_s"] = round(run.seconds, 2)
        result["peak_rss_mb"] = round(run.peak_rss / 2**20)
    shutil.rmtree(out, ignore_errors=True)
    return result
