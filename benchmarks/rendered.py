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
  - enlargement: ``benchmarks.enlarge``'s experiment per material seed and photo set (the
    top-light photo; it and nine other lights): its error, the copy oracle, the per-texel
    lookup, tiling, the gap share and realism, and the gap's worst and median over the seeds;
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


def _procedural(args) -> str:
    """The first procedural material of ``--materials`` (throughput and noise; leather if none)."""
    from tasks.materials import MATERIALS

    return next((m for m in args.materials.split(",") if m in MATERIALS), "leather")


def _first_seed(args) -> int:
    return int(str(args.seeds).split(",")[0])
PARTS = ("throughput", "noise", "benches")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--materials", default="leather,stone,fabric,bumps",
                        help="materials (default: leather,stone,fabric,bumps; bumps: smooth "
                             "bumps of two scales under scikit-image's grass photo as albedo, "
                             "brick: the brick photo with its own lightness as relief)")
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
    parser.add_argument("--seeds", default="1",
                        help="material seeds, a row each (default 1; the photo's own relief "
                             "of brick has none)")
    parser.add_argument("--compare", default="--qp-metric plain", metavar="OPTIONS",
                        help="btf enlarge options of a second enlargement of the same stores, "
                             "reported beside the default's (default: the paper's plain QP; "
                             "'' for none)")
    parser.add_argument("--sets", default="top,random",
                        help="the enlargement's photos: top (the top light's layer), random "
                             "(it and 9 other lights), mean (default top,random)")
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
    material = _procedural(args)
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

    name = _procedural(args)
    s = parse_sampling(args.sampling)
    material = Material(name, seed=_first_seed(args))
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
    material_seeds = [int(v) for v in str(args.seeds).split(",")]
    out = []
    for material in args.materials.split(","):
        for renderer, bsdf in renderers(args):
            for seed in material_seeds if material != "brick" else material_seeds[:1]:
                work = tmp / f"{material}-{renderer}-{bsdf}-{seed}"
                work.mkdir()
                extra = (("--renderer", "mitsuba", "--spp", args.spp, "--bsdf", bsdf)
                         if renderer == "mitsuba" else ())
                name = renderer if bsdf is None else f"mitsuba, {bsdf}"
                start = time.perf_counter()
                e = enlarge._material(material, argparse.Namespace(
                    size=args.size, rank=args.rank, sets=args.sets, baselines="tiling,lookup",
                    enlarge_options="", sheet=None, seed=seed), work, generate=extra)
                runs = {"": e}
                if args.compare.strip():
                    again = work / "compare"
                    again.mkdir()
                    (again / "M.zarr").symlink_to(work / "M.zarr")
                    runs[args.compare.strip()] = enlarge._material(material, argparse.Namespace(
                        size=args.size, rank=args.rank, sets=args.sets, baselines="lookup",
                        enlarge_options=args.compare, sheet=None, seed=seed), again,
                        generate=None)
                sets = {}
                for options, run in runs.items():
                    for which, r in run["sets"].items():
                        # one oracle for both: the lower (each is the copy through a QP)
                        best = min(r2["oracle"]["error"] for r2 in
                                   (x["sets"][which] for x in runs.values()))
                        sets[which + (f" ({options})" if options else "")] = {
                            "error": r["final"]["error"], "realism": r["final"]["realism"],
                            "oracle": best, "lookup": r["lookup"]["error"],
                            "tiling": e["baselines"]["tiling"]["error"],
                            "gap": gap_share(r["final"]["error"], r["lookup"]["error"], best),
                            "seconds": r["wall"]}
                row = {"material": material, "renderer": name, "seed": seed,
                       "compression": _compression(work / "M.zarr", work, ranks),
                       "enlarge": sets,
                       "quilt": _quilting(work / "M.zarr", seeds)}
                row["seconds"] = time.perf_counter() - start
                log(f"rendered: {material} ({name}, seed {seed}) done in "
                    f"{row['seconds']:.0f} s; gap " + ", ".join(
                        f"{k} {v['gap']:.2f}" for k, v in sets.items()))
                out.append(row)
                shutil.rmtree(work)
    return out


def gap_summary(benches: list[dict]) -> list[dict]:
    """Worst and median gap share per material, renderer and photo set, over the seeds."""
    groups: dict[tuple, list[float]] = {}
    for b in benches:
        for which, e in b["enlarge"].items():
            groups.setdefault((b["material"], b["renderer"], which), []).append(e["gap"])
    return [{"material": m, "renderer": r, "set": w, "seeds": len(g),
             "worst": float(max(g)), "median": float(np.median(g))}
            for (m, r, w), g in groups.items()]


def run(args: argparse.Namespace) -> dict:
    """All parts in this run (see the module)."""
    parts = set(args.parts.split(","))
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-rendered-"))
    result = {"suite": SUITE, "sampling": args.sampling, "bsdf": args.bsdf, "spp": args.spp,
              "seeds": args.seeds, "sets": args.sets, "compare": args.compare,
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
        lines += ["", "Enlargement (photos: top = the top light's layer, random = it and 9 "
                      "other lights; eq. (11) error; gap = (E - oracle) / (lookup - oracle)):",
                  "",
                  "| material | renderer | seed | photos | enlarge | oracle | lookup | tiling | "
                  "gap | realism | s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for b in result["benches"]:
            for which, e in b["enlarge"].items():
                lines.append(f"| {b['material']} | {b['renderer']} | {b.get('seed', '')} | "
                             f"{which} | {e['error']:.4f} | {e['oracle']:.4f} | "
                             f"{e['lookup']:.4f} | {e['tiling']:.4f} | {e['gap']:.2f} | "
                             f"{e['realism']:.2f} | {e['seconds']:.0f} |")
        lines += ["", "Gap share over the seeds:", "",
                  "| material | renderer | photos | seeds | worst | median |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {g['material']} | {g['renderer']} | {g['set']} | {g['seeds']} | "
                  f"{g['worst']:.2f} | {g['median']:.2f} |"
                  for g in gap_summary(result["benches"])]
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
