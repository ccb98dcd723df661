"""Mitsuba 3: btf's BSDF against the plugin people use (elerac/btf-rendering), one material.

One synthetic UBO2003-style zip of JPEGs (:func:`benchmarks.archives.write_archive`: the
81 x 81 hemisphere, ``--size`` texels) is rendered by both, each in its own process on the
``llvm_ad_rgb`` variant:

- **btf**: ``btf ingest`` of the zip (float16), ``btf compress --rank R``, the ``btf`` BSDF
  (:mod:`tasks.btf_bsdf`, Dr.Jit, compiled into the render kernel);
- **peer**: elerac/btf-rendering's ``measuredbtf`` (a checkout given by ``--peer``: it loads
  every image of the zip, finds the k = 4 nearest measured (light, view) pairs in a 6-D k-d
  tree with inverse-distance weights, p = 4, nearest texel, in numpy outside Dr.Jit).

Figures:

- **time per frame** on the peer's own ``simple_sphere`` scene (path tracer, a constant and a
  point emitter, the sphere textured 5 times round, a checkerboard floor) at ``--resolution``
  and ``--spp``: the first frame (loading, compiling) and the median of the next ``--frames``;
- **peak memory** of each process (``ru_maxrss``);
- **continuity**: a plane seen from straight above under a directional light swept over
  ``--sweep`` degrees in 1-degree steps of theta across a measured ring (``--sweep-theta``), direct
  illumination, the same sampler seed every frame (so frames differ by the BSDF only): the
  largest change of a pixel between consecutive frames, relative to the frame's mean (and the
  median step, for scale). A blend that is continuous in the directions changes a little at
  every step; nearest-neighbour sets that switch change a lot at one step.

``btf`` and the peer treat values differently (the peer divides by pi and decodes gamma 2.2;
btf's layers are radiance under unit irradiance), so images are compared with themselves
only. Needs ``pip install 'btf-pipeline[mitsuba]' opencv-python-headless tqdm`` and
LLVM 16+ (docs/mitsuba.md). Without ``--peer`` only btf is measured.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import git_revision, machine
from tasks.sampling import direction_vectors

SUITE = "mitsuba"
ROOT = Path(__file__).resolve().parents[1]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The suite's options."""
    parser.add_argument("--peer", default=os.environ.get("BTF_PEER_BTF_RENDERING"),
                        help="a checkout of elerac/btf-rendering (default: "
                             "$BTF_PEER_BTF_RENDERING; none: btf alone)")
    parser.add_argument("--size", type=int, default=256, help="texels of the zip's images")
    parser.add_argument("--views", type=int, default=81, help="view directions of the zip")
    parser.add_argument("--lights", type=int, default=81, help="light directions of the zip")
    parser.add_argument("--rank", type=int, default=16, help="btf's components")
    parser.add_argument("--resolution", type=int, default=256, help="image side, pixels")
    parser.add_argument("--spp", type=int, default=16, help="samples per pixel")
    parser.add_argument("--frames", type=int, default=3, help="frames timed after the first")
    parser.add_argument("--sweep", type=int, default=30,
                        help="degrees of the light sweep (default: ring to ring, 30 to 60)")
    parser.add_argument("--sweep-theta", type=float, default=45.0,
                        help="theta the sweep is centred on (a measured ring: 45 of UBO2003's)")
    parser.add_argument("--workdir", default=tempfile.gettempdir(), help="for the stores")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke test: a 9 x 9 zip of 64^2, 64^2 images, 2 frames")


def _sphere_scene(mi, bsdf) -> dict:
    """elerac/btf-rendering's ``simple_sphere`` scene, with ``bsdf`` on the sphere."""
    return {
        "type": "scene", "integrator": {"type": "path"},
        "sensor": {"type": "perspective",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[-3.5, 2, 3.5],
                                                              target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 0, "height": 0}},
        "constant_emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 0.5}},
        "point_emitter": {"type": "point", "position": [-2, 2, 0],
                          "intensity": {"type": "rgb", "value": [10, 10, 10]}},
        "sphere": {"type": "sphere", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 90),
                   "bsdf": bsdf},
        "floor": {"type": "rectangle",
                  "to_world": (mi.ScalarTransform4f().translate([0, -1, 0])
                               @ mi.ScalarTransform4f().rotate([1, 0, 0], -90)
                               @ mi.ScalarTransform4f().scale(2)),
                  "bsdf": {"type": "diffuse",
                           "reflectance": {"type": "checkerboard",
                                           "to_uv": mi.ScalarTransform4f().scale(5)}}},
    }


def _plane_scene(mi, bsdf, theta: float, resolution: int) -> dict:
    return {"type": "scene", "integrator": {"type": "direct"},
            "sensor": {"type": "orthographic",
                       "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 2],
                                                                  target=[0, 0, 0],
                                                                  up=[0, 1, 0]),
                       "sampler": {"type": "independent", "sample_count": 4},
                       "film": {"type": "hdrfilm", "width": resolution, "height": resolution,
                                "rfilter": {"type": "box"}}},
            "light": {"type": "directional",
                      "direction": (-direction_vectors(theta, 0.0)).tolist(),
                      "irradiance": {"type": "rgb", "value": 1.0}},
            "shape": {"type": "rectangle", "bsdf": bsdf}}


def worker() -> None:
    """In a fresh process: render with one BSDF (``sys.argv[1]``: JSON settings), print JSON."""
    import resource

    s = json.loads(sys.argv[1])
    from pipeline import mitsuba_plugin

    mitsuba_plugin.variant("llvm_ad_rgb")
    import mitsuba as mi

    started = time.perf_counter()
    if s["kind"] == "btf":
        def make(uv_scale):
            return mitsuba_plugin.bsdf(s["store"], uv_scale=uv_scale)
    else:
        sys.path.insert(0, s["peer"])
        from custom_bsdf.measuredbtf import MeasuredBTF

        mi.register_bsdf("measuredbtf", lambda props: MeasuredBTF(props))
        loaded = {}

        def make(uv_scale):  # one load of the zip, as a scene would have
            if uv_scale not in loaded:
                loaded[uv_scale] = mi.load_dict({
                    "type": "measuredbtf", "filename": s["zip"],
                    "to_uv": mi.ScalarTransform4f().scale(uv_scale)})
            return loaded[uv_scale]
    sphere = make(5.0)
    load = time.perf_counter() - started
    scene_dict = _sphere_scene(mi, sphere)
    scene_dict["sensor"]["film"].update(width=s["resolution"], height=s["resolution"])
    scene = mi.load_dict(scene_dict)
    times = []
    for frame in range(1 + s["frames"]):
        t = time.perf_counter()
        image = np.asarray(mi.render(scene, spp=s["spp"], seed=frame))
        times.append(time.perf_counter() - t)
    np.save(s["out"] + "_sphere.npy", image)
    plane = make(1.0)
    frames = []
    for step in range(s["sweep"] + 1):
        theta = s["sweep_theta"] - s["sweep"] / 2 + step
        scene = mi.load_dict(_plane_scene(mi, plane, theta, s["plane"]))
        frames.append(np.asarray(mi.render(scene, spp=4, seed=0)))
    frames = np.stack(frames)
    np.save(s["out"] + "_sweep.npy", frames)
    # pixels that are not finite (NaN, inf) are counted apart and left out of the steps
    bad = ~np.isfinite(frames)
    clean = np.where(bad, np.nan, frames)
    means = np.nanmean(clean, axis=(1, 2, 3))
    steps = np.abs(np.diff(clean, axis=0)) / means[1:, None, None, None]
    steps = np.where(np.isfinite(steps), steps, 0.0)
    print(json.dumps({
        "nonfinite_frames": [float(s["sweep_theta"] - s["sweep"] / 2 + i)
                             for i in range(len(frames)) if bad[i].any()],
        "nonfinite_pixels": int(bad.any(axis=-1).sum()),
        "load_s": load, "first_frame_s": times[0], "frame_s": float(np.median(times[1:])),
        "peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "largest_step": float(steps.max()),
        "largest_step_at": (s["sweep_theta"] - s["sweep"] / 2 + 1
                            + int(np.argmax(steps.max(axis=(1, 2, 3))))),
        "median_step": float(np.median(steps.max(axis=(1, 2, 3)))),
        "mean_step": float(steps.mean()),
        "sphere_mean": float(image.mean())}))


def _run_worker(settings: dict) -> dict:
    code = "from benchmarks.mitsuba import worker; worker()"
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", code, json.dumps(settings)],
                          capture_output=True, text=True, cwd=ROOT)
    if done.returncode != 0:
        raise RuntimeError(f"the {settings['kind']} render failed:\n{done.stderr[-3000:]}")
    out = json.loads(done.stdout.strip().splitlines()[-1])
    out["process_s"] = time.perf_counter() - started
    return out


def run(args: argparse.Namespace) -> dict:
    """Both renderers on one material, each in its own process."""
    from benchmarks.archives import write_archive
    from pipeline.cli import main

    if args.quick:
        args.size, args.views, args.lights, args.resolution = 64, 9, 9, 64
        args.frames, args.spp, args.sweep, args.sweep_theta = 2, 4, 4, 15.0
    result = {"suite": SUITE, "quick": bool(args.quick), "machine": machine(),
              "revision": git_revision(),
              "settings": {k: getattr(args, k) for k in ("size", "views", "lights", "rank",
                                                         "resolution", "spp", "frames",
                                                         "sweep", "sweep_theta")}}
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-mitsuba-", dir=args.workdir))
    try:
        zip_path = write_archive(tmp / "UBO_SYNTH.zip", size=args.size, views=args.views,
                                 lights=args.lights)
        t = time.perf_counter()
        for argv in (["ingest", str(zip_path), str(tmp / "s.zarr"), "-q"],
                     ["compress", str(tmp / "s.zarr"), str(tmp / "c.zarr"), "--rank",
                      str(args.rank), "-q"]):
            if main(argv) != 0:
                raise RuntimeError(f"btf {' '.join(argv)} failed")
        result["prepare_s"] = time.perf_counter() - t
        result["zip_mb"] = zip_path.stat().st_size / 1e6
        common = {"resolution": args.resolution, "spp": args.spp, "frames": args.frames,
                  "sweep": args.sweep, "sweep_theta": args.sweep_theta,
                  "plane": min(args.size, 256)}
        result["btf"] = _run_worker({**common, "kind": "btf", "store": str(tmp / "c.zarr"),
                                     "out": str(tmp / "btf")})
        if args.peer:
            result["peer"] = _run_worker({**common, "kind": "peer", "peer": args.peer,
                                          "zip": str(zip_path), "out": str(tmp / "peer")})
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result


def report(result: dict) -> str:
    """A Markdown table of a result."""
    s, m = result["settings"], result["machine"]
    lines = [f"Mitsuba 3, llvm_ad_rgb (at {result['revision']}, {m['cpus']} cores, {m['when']}"
             f"{', --quick' if result['quick'] else ''}): a UBO2003-style zip of "
             f"{s['views']} x {s['lights']} JPEGs of {s['size']}^2 ({result['zip_mb']:.0f} MB); "
             f"btf: ingested and compressed to rank {s['rank']} first "
             f"({result['prepare_s']:.1f} s). Sphere scene {s['resolution']}^2 at {s['spp']} "
             f"spp; a light sweep of {s['sweep']} degrees in 1-degree steps of theta across "
             f"{s['sweep_theta']:g} (phi 0), plane {min(s['size'], 256)}^2, direct light.",
             "",
             "| renderer | load s | first frame s | frame s (median of next) | peak RSS | "
             "largest step | median step | largest / median |",
             "|---|---|---|---|---|---|---|---|"]
    notes: list[str] = []
    for name, label in (("btf", "btf BSDF (Dr.Jit)"), ("peer", "elerac/btf-rendering")):
        r = result.get(name)
        if r is None:
            continue
        if r.get("nonfinite_frames"):
            where = ", ".join(f"{t:g}" for t in r["nonfinite_frames"])
            notes.append(f"{label}: {r['nonfinite_pixels']} pixels not finite (NaN or inf) "
                         f"in the frames at theta {where} (left out of its steps)")
        lines.append(f"| {label} | {r['load_s']:.2f} | {r['first_frame_s']:.2f} | "
                     f"{r['frame_s']:.3f} | {r['peak_rss'] / 2**20:.0f} MiB | "
                     f"{r['largest_step']:.3f} (at {r['largest_step_at']:.0f} deg) | "
                     f"{r['median_step']:.3f} | "
                     f"{r['largest_step'] / max(r['median_step'], 1e-12):.1f} |")
    lines += ["", *notes] if notes else []
    if "peer" in result:
        b, p = result["btf"], result["peer"]
        lines += ["", f"Per frame btf is {p['frame_s'] / b['frame_s']:.1f}x faster; peak memory "
                      f"{b['peak_rss'] / p['peak_rss']:.2f}x the peer's; largest frame-to-frame "
                      f"change {b['largest_step'] / p['largest_step']:.2f}x the peer's."]
    else:
        lines += ["", "(no --peer checkout given: btf alone)"]
    return "\n".join(lines)
