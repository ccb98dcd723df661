"""Materials path traced by Mitsuba 3 beside btf's own shading: throughput, noise, benches.

``btf generate --renderer mitsuba`` renders a procedural material's height field with
Mitsuba's path tracer (masking, cast shadows, interreflections, a physically based BSDF);
``--renderer shading`` (the default) is btf's own model. In one run:

- **throughput**: layers per second of both renderers on the same material, size and
  sampling, and the path tracer's samples per second;
- **noise**: the path tracer's relative noise per layer at several spp (two seeds of one
  store: ``rms(a - b) / sqrt 2 / rms((a + b) / 2)``, median and worst over the layers), and the
  spp a noise below 1% needs (the worst layer, from the largest spp measured: noise falls
  as 1 / sqrt spp);
- **benches**, for every material under both renderers, on a ``--size`` store:
  - compression: eq. (11) error of the rank-k truncation of one ``btf compress`` against the
    store, for every k of ``--ranks``, absolute and relative to the store's mean texel RMS;
  - enlargement: ``benchmarks.enlarge``'s experiment with the top-light photo (its error,
    the copy oracle, the per-texel lookup, tiling, the gap share and realism);
  - quilting: ``benchmarks.seams``' V = 2 tile-set figures on three layers of the store
    (top, middle and lowest light of the top view), over ``--quilt-seeds`` seeds drawn at
    random from a wide range: worst and median seam and structure.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import btf_executable, git_revision, machine, measure

SUITE = "rendered"
def renderers(args) -> list[tuple[str, str | None]]:
    """The benches' rows per material: btf's shading, then the path tracer per BSDF."""
    return [("shading", None)] + [("mitsuba", b) for b in args.bsdf.split(",")]


def _first_bsdf(args) -> str:
    return args.bsdf.split(",")[0]
PARTS = ("throughput", "noise", "benches")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--materials", default="leather,stone,fabric",
                        help="procedural materials (default: leather,stone,fabric)")
    parser.add_argument("--bsdf", default="principled,conductor",
                        help="the path tracer's BSDFs for the benches, a row each (the first "
                             "for throughput and noise; default principled,conductor)")
    parser.add_argument("--spp", type=int, default=256,
                        help="spp of the benches' renders (default 256: noise under 1%%)")
    parser.add_argument("--throughput-spp", type=int, default=64,
                        help="spp of the throughput run (default 64, generate's default)")
    parser.add_argument("--sampling", default="abtf:12,4")
    parser.add_argument("--throughput-size", type=int, default=256)
    parser.add_argument("--noise-spp", default="4,16,64,256")
    parser.add_argument("--noise-size", type=int, default=64)
    parser.add_argument("--size", type=int, default=128, help="side of the benches' stores")
    parser.add_argument("--ranks", default="4,8,16,32")
    parser.add_argument("--rank", type=int, default=16, help="rank of the enlargement's sample")
    parser.add_argument("--quilt-seeds", type=int, default=5)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--parts", default=",".join(PARTS))


def _generate(out: Path, material: str, size: int, sampling: str, renderer: str, *,
              spp: int | None = None, bsdf: str | None = None, seed: int = 1) -> list[str]:
    argv = [btf_executable(), "generate", str(out), "--material", material, "--size", str(size),
            "--sampling", sampling, "--seed", str(seed), "--quiet", "--overwrite"]
    if renderer == "mitsuba":
        argv += ["--renderer", "mitsuba", "--spp", str(spp or 64), "--bsdf", bsdf or "principled"]
    return argv


def _throughput(args, tmp: Path) -> list[dict]:
    from tasks.sampling import parse_sampling

    s = parse_sampling(args.sampling)
    layers = s.theta_view.size * s.theta_light.size
    rows = []
    material = args.materials.split(",")[0]
    for renderer in ("shading", "mitsuba"):
        m = measure(_generate(tmp / "t.zarr", material, args.throughput_size, args.sampling,
                              renderer, spp=args.throughput_spp, bsdf=_first_bsdf(args)))
        rows.append({"renderer": renderer, "seconds": m.seconds, "peak_rss": m.peak_rss,
                     "layers_per_s": layers / m.seconds,
                     "samples_per_s": (layers * args.throughput_size**2 * args.throughput_spp
                                       / m.seconds
                                       if renderer == "mitsuba" else None)})
        shutil.rmtree(tmp / "t.zarr")
    return rows


def layer_noise(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Relative noise of each layer of two independent renders ``(views, lights, y, x, c)``."""
    diff = np.sqrt(np.mean((a - b) ** 2, axis=(2, 3, 4))) / np.sqrt(2)
    signal = np.sqrt(np.mean(((a + b) / 2) ** 2, axis=(2, 3, 4)))
    return (diff / np.maximum(signal, 1e-12)).ravel()


def _noise(args) -> dict:
    """Two sampler seeds of the same surface, in this process, per spp."""
    from pipeline.mitsuba_plugin import variant
    from tasks.materials import Material
    from tasks.pathtrace import PathTracer, render_block
    from tasks.sampling import parse_sampling
    from tasks.shading import ShadingModel

    name = args.materials.split(",")[0]
    s = parse_sampling(args.sampling)
    material = Material(name, seed=args.seed)
    halo = ShadingModel(relief=material.relief).halo(float(s.theta_view.max()),
                                                    float(s.theta_light.max())) + 8
    n = args.noise_size
    fields = material.fields(-halo, -halo, n + 2 * halo, n + 2 * halo)
    chosen = variant("auto")
    rows = []
    for spp in (int(v) for v in args.noise_spp.split(",")):
        renders = [render_block(fields, halo=halo, theta_view=s.theta_view, phi_view=s.phi_view,
                                theta_light=s.theta_light, phi_light=s.phi_light,
                                view_index=np.arange(s.theta_view.size),
                                light_index=np.arange(s.theta_light.size), origin=(0, 0),
                                tracer=PathTracer(relief=material.relief, bsdf=_first_bsdf(args),
                                                  spp=spp, seed=seed, variant=chosen))
                   for seed in (1, 2)]
        noise = layer_noise(*(r.astype(np.float64) for r in renders))
        rows.append({"spp": spp, "median": float(np.median(noise)), "worst": float(noise.max())})
    last = rows[-1]
    needed = int(np.ceil(last["spp"] * (last["worst"] / 0.01) ** 2))
    return {"material": name, "size": n, "rows": rows, "spp_for_1_percent": needed}


def _compression(store: Path, tmp: Path, ranks: list[int]) -> list[dict]:
    from benchmarks.enlarge import _btf, _factors, truth_rows
    from tasks.evaluation import abrdf_error

    out = tmp / "c.zarr"
    _btf("compress", store, out, "--rank", max(ranks), "--overwrite")
    u, s, v, transform, _ = _factors(out)
    truth = truth_rows(store)
    mask = np.ones(truth.shape[:2], bool)
    scale = float(np.mean(np.sqrt(np.mean(truth**2, axis=-1))))
    rows = []
    for k in ranks:
        uk = u.reshape(-1, u.shape[-1])[:, :k]
        err = abrdf_error(uk, v[..., :k] * s[:k].astype(np.float32), transform, truth, mask)
        rows.append({"rank": k, "error": err, "relative": err / scale})
    shutil.rmtree(out)
    return rows


def quilt_reference(store: Path) -> np.ndarray:
    """Three layers of the top view (top, middle and lowest light) as a quilting reference."""
    import zarr

    g = zarr.open_group(store, mode="r")
    theta = np.asarray(g["theta_light"][...])
    order = np.argsort(theta, kind="stable")
    picks = [int(order[0]), int(order[len(order) // 2]), int(order[-1])]
    view = int(np.argmin(np.asarray(g["theta_view"][...])))
    layers = np.asarray(g["radiance"][view, picks], np.float32).mean(axis=-1)
    scale = np.percentile(layers, 99.5, axis=(1, 2))[:, None, None]
    return np.clip(layers / np.maximum(scale, 1e-6), 0, 1).transpose(1, 2, 0)


def _quilting(store: Path, seeds: list[int]) -> dict:
    from benchmarks.seams import seed_figures, summary
    from tasks.quilt_layout import sample_lattice

    reference = quilt_reference(store)
    lattice = sample_lattice(reference)
    rows = [seed_figures(store.stem, reference, lattice, block=None, overlap=None, corners=2,
                         seed=seed) for seed in seeds]
    return {"seeds": rows, **summary(rows)}


def _benches(args, tmp: Path, log) -> list[dict]:
    from benchmarks import enlarge
    from tasks.evaluation import gap_share

    ranks = [int(v) for v in args.ranks.split(",")]
    seeds = [int(v) for v in np.random.default_rng().integers(0, 2**31 - 1, args.quilt_seeds)]
    out = []
    for material in args.materials.split(","):
        for renderer, bsdf in renderers(args):
            work = tmp / f"{material}-{renderer}-{bsdf}"
            work.mkdir()
            extra = (("--renderer", "mitsuba", "--spp", args.spp, "--bsdf", bsdf)
                     if renderer == "mitsuba" else ())
            renderer = renderer if bsdf is None else f"mitsuba, {bsdf}"
            start = time.perf_counter()
            e = enlarge._material(material, argparse.Namespace(
                size=args.size, rank=args.rank, sets="top", baselines="tiling,lookup",
                enlarge_options="", sheet=None, seed=args.seed), work, generate=extra)
            top = e["sets"]["top"]
            row = {"material": material, "renderer": renderer,
                   "compression": _compression(work / "M.zarr", work, ranks),
                   "enlarge": {"error": top["final"]["error"],
                               "realism": top["final"]["realism"],
                               "oracle": top["oracle"]["error"],
                               "lookup": top["lookup"]["error"],
                               "tiling": e["baselines"]["tiling"]["error"],
                               "gap": gap_share(top["final"]["error"], top["lookup"]["error"],
                                                top["oracle"]["error"]),
                               "seconds": top["wall"]},
                   "quilt": _quilting(work / "M.zarr", seeds)}
            row["seconds"] = time.perf_counter() - start
            log(f"rendered: {material} ({renderer}) done in {row['seconds']:.0f} s")
            out.append(row)
            shutil.rmtree(work)
    return out


def run(args: argparse.Namespace) -> dict:
    """All parts in this run (see the module)."""
    parts = set(args.parts.split(","))
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-rendered-"))
    result = {"suite": SUITE, "sampling": args.sampling, "bsdf": args.bsdf, "spp": args.spp,
              "throughput_spp": args.throughput_spp,
              "size": args.size, "throughput_size": args.throughput_size,
              "machine": machine(), "git": git_revision()}
    try:
        if "throughput" in parts:
            result["throughput"] = _throughput(args, tmp)
        if "noise" in parts:
            result["noise"] = _noise(args)
        if "benches" in parts:
            result["benches"] = _benches(args, tmp, log=print)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result


def report(result: dict) -> str:
    """Markdown tables of a result."""
    mib = 1 << 20
    lines = []
    if "throughput" in result:
        lines += [f"Throughput: `btf generate OUT --material M --size "
                  f"{result['throughput_size']} --sampling {result['sampling']}` (mitsuba: "
                  f"`--renderer mitsuba --spp {result['throughput_spp']} --bsdf "
                  f"{result['bsdf'].split(',')[0]}`).",
                  "",
                  "| renderer | wall s | layers/s | path samples/s | peak RSS |",
                  "|---|---|---|---|---|"]
        for r in result["throughput"]:
            samples = f"{r['samples_per_s'] / 1e6:.2f} M" if r["samples_per_s"] else "-"
            lines.append(f"| {r['renderer']} | {r['seconds']:.1f} | {r['layers_per_s']:.2f} | "
                         f"{samples} | {r['peak_rss'] / mib:.0f} MiB |")
        lines.append("")
    if "noise" in result:
        n = result["noise"]
        lines += [f"Noise of the path tracer ({n['material']}, {n['size']}^2, two sampler "
                  "seeds per spp): relative RMS difference per layer / sqrt 2.", "",
                  "| spp | median layer | worst layer |", "|---|---|---|"]
        lines += [f"| {r['spp']} | {100 * r['median']:.2f}% | {100 * r['worst']:.2f}% |"
                  for r in n["rows"]]
        lines += ["", f"A noise below 1% in the worst layer needs about "
                      f"{n['spp_for_1_percent']} spp (1 / sqrt spp from the largest spp).", ""]
    if "benches" in result:
        ranks = [c["rank"] for c in result["benches"][0]["compression"]]
        lines += [f"Benches on {result['size']}^2 stores, `{result['sampling']}`; mitsuba: "
                  f"{result['spp']} spp, 2 bounces.", "",
                  "Compression, eq. (11) error relative to the store's mean texel RMS:", "",
                  "| material | renderer | " + " | ".join(f"rank {k}" for k in ranks) + " |",
                  "|---|---|" + "---|" * len(ranks)]
        for b in result["benches"]:
            lines.append(f"| {b['material']} | {b['renderer']} | " + " | ".join(
                f"{100 * c['relative']:.2f}%" for c in b["compression"]) + " |")
        lines += ["", "Enlargement (top-light photo; eq. (11) error; gap = (E - oracle) / "
                      "(lookup - oracle)):", "",
                  "| material | renderer | enlarge | oracle | lookup | tiling | gap | realism | "
                  "s |", "|---|---|---|---|---|---|---|---|---|"]
        for b in result["benches"]:
            e = b["enlarge"]
            lines.append(f"| {b['material']} | {b['renderer']} | {e['error']:.4f} | "
                         f"{e['oracle']:.4f} | {e['lookup']:.4f} | {e['tiling']:.4f} | "
                         f"{e['gap']:.2f} | {e['realism']:.2f} | {e['seconds']:.0f} |")
        lines += ["", "Quilting, V = 2 tile sets on three layers of the store, the same "
                      "random seeds for every row:", "",
                  "| material | renderer | failed | seam: worst / median | "
                  "structure: worst / median |", "|---|---|---|---|---|"]
        for b in result["benches"]:
            q = b["quilt"]

            def cell(key, q=q):
                return "-" if q[key] is None else f"{q[key]['worst']:.2f} / {q[key]['median']:.2f}"
            lines.append(f"| {b['material']} | {b['renderer']} | {len(q['failed'])} of "
                         f"{len(q['seeds'])} | {cell('seam')} | {cell('structure')} |")
    return "\n".join(lines)


def rates(result: dict) -> dict[str, float]:
    """The path tracer's rate for ``btf run --plan``: samples per core-second."""
    rows = [r for r in result.get("throughput", []) if r["samples_per_s"]]
    if not rows:
        return {}
    return {"generate_path_samples_per_core_second":
            rows[0]["samples_per_s"] / result["machine"]["cpus"]}
