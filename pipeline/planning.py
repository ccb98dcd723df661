"""``btf run --plan``: what each stage of a config will read, write and hold, before it runs.

Per stage: the bytes read and written (float32 values, before compression), the tasks, the
passes over its input, the peak memory of one task and of the client, and an estimated time
from rates measured on this machine by ``btf bench`` (stored in :func:`rates_path`; built-in
rates, measured on the project's 2-core test machine and listed in BENCHMARKS.md, stand in for
suites not yet run here). Shapes come from the input stores' metadata, or from the plan of the
earlier stage that makes them: nothing is read or computed.

A plan whose per-worker memory exceeds the workers' limit (or whose client memory exceeds the
machine's) is refused before anything runs, naming the stage and the option to change.
Stages without an estimate (their cost depends on data: roller detection, enlargement's
Texture Optimization, rendering) are listed as such.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any

from pipeline.errors import BTFError

GiB = 1 << 30
BASE_PROCESS = 300 << 20  # interpreter, numpy, dask, zarr: a worker's memory before any task
BUILT_IN_RATES = {  # per core, btf bench on the 2-core test VM, 2026-11-23 (BENCHMARKS.md)
    "generate_texel_directions_per_core_second": 6.2e6,
    "compress_bytes_per_core_second": 0.37e9,
    # --passes 1 (K = 64: k = 385, s = 771, sparse sign maps; 30603 x 65536, 8 GB)
    "compress_one_pass_bytes_per_core_second": 0.13e9,
    "quilt_plan_seconds_per_texel_pair": 5.45e-11,  # per (tile texel x sample texel)
    "quilt_values_per_core_second": 3.1e6,
}


def rates_path() -> Path:
    """Where ``btf bench`` keeps the rates it measured: ``$BTF_RATES`` or the user cache."""
    if os.environ.get("BTF_RATES"):
        return Path(os.environ["BTF_RATES"])
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "btf" / "rates.json"


def record_rates(rates: dict[str, float], suite: str) -> Path:
    """Store rates measured by a ``btf bench`` suite (merged with those already stored)."""
    path = rates_path()
    stored = _stored()
    for key, value in rates.items():
        stored[key] = {"value": float(value), "suite": suite,
                       "when": time.strftime("%Y-%m-%d %H:%M")}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(stored, indent=2) + "\n")
    tmp.replace(path)
    return path


def _stored() -> dict:
    try:
        return json.loads(rates_path().read_text())
    except (OSError, ValueError):
        return {}


def rate(key: str) -> tuple[float, str]:
    """A rate and where it comes from (measured here by ``btf bench``, or built in)."""
    stored = _stored().get(key)
    if isinstance(stored, dict) and stored.get("value", 0) > 0:
        return stored["value"], f"measured by btf bench {stored.get('suite')} {stored.get('when')}"
    return BUILT_IN_RATES[key], "built-in (the test machine's)"


@dataclasses.dataclass(frozen=True)
class Shape:
    """What a stage needs to know of a store: its kind and array shapes."""

    kind: str
    radiance: tuple[int, ...]  # (view, light, y, x, channel), also for compressed stores
    chunk: int
    dir_chunk: int
    rank: int | None = None
    unit: int = 0  # texels per side of a write unit (the shard, else the chunk)
    truth: bool = False  # ground-truth fields (generated stores, and crops of them)

    @property
    def side(self) -> int:
        """Texels per side of a task block (as :func:`pipeline.graphs.blocks.task_block`)."""
        return _task_side(self.unit or self.chunk)


@dataclasses.dataclass
class StagePlan:
    """The estimate of one stage."""

    name: str
    where: str
    read: int = 0
    written: int = 0
    tasks: int = 0
    passes: int = 0
    reads: int = 0  # reads of the input (a pass may read it twice)
    task_bytes: int = 0
    client_bytes: int = 0
    core_seconds: float | None = None  # work that parallelises over the workers' cores
    serial_seconds: float = 0.0  # work on the client alone (quilt planning)
    rate_source: str = ""
    option: str = ""
    note: str = ""
    # the same stage in its other mode (compress: one pass or several), for the user to compare
    alternatives: list[StagePlan] = dataclasses.field(default_factory=list)


def shape_of(path: str) -> Shape | None:
    """The shape of an existing store from its metadata (None if it is no store btf knows)."""
    from pipeline.stores.base import open_group

    try:
        group = open_group(path)
    except BTFError:
        return None
    kind = group.attrs.get("btf_kind")
    if "radiance" in group and kind in ("abtf", "btf"):
        a = group["radiance"]
        return Shape(kind, tuple(a.shape), a.chunks[2], a.chunks[1],
                     unit=(a.shards or a.chunks)[2], truth="height" in group)
    if kind == "compressed":
        u, v = group["U"], group["V"]
        return Shape(kind, (u.shape[0], u.shape[1], v.shape[0], v.shape[1], u.shape[2]),
                     v.chunks[0], u.chunks[1], rank=u.shape[3])
    return Shape(str(kind), (), 0, 0)


def _task_side(chunk: int) -> int:
    from pipeline.graphs.blocks import TASK_TEXELS

    return chunk * max(1, TASK_TEXELS // chunk)


def _generate(params, shapes: dict) -> tuple[StagePlan, Shape]:
    from tasks.sampling import parse_sampling

    s = parse_sampling(params.sampling)
    nv, nl, n = s.theta_view.size, s.theta_light.size, params.size**2
    nc = 3
    side = min(_task_side(params.shard or params.chunk), params.size)
    spatial = math.ceil(params.size / side) ** 2
    light_blocks = math.ceil(nl / params.dir_chunk)
    block = side * side * min(params.dir_chunk, nl) * nc * 4
    per_core, source = rate("generate_texel_directions_per_core_second")
    plan = StagePlan("generate", "", written=nv * nl * n * nc * 4 + n * 6 * 4,
                     tasks=nv * light_blocks * spatial + spatial, passes=1, reads=0,
                     task_bytes=4 * block + (side + 64) ** 2 * 6 * 4,
                     client_bytes=0, core_seconds=nv * nl * n / per_core, rate_source=source,
                     option="--chunk / --dir-chunk (smaller task blocks)")
    return plan, Shape("btf", (nv, nl, params.size, params.size, nc), params.chunk,
                       params.dir_chunk, unit=params.shard or params.chunk, truth=True)


def _compress(params, shapes: dict, *, alternative: bool = True) -> tuple[StagePlan, Shape]:
    from pipeline.graphs.row_passes import FAN_IN, memory_estimate, plan_row_blocks
    from pipeline.graphs.tile_passes import (
        plan_tile_rows,
        sketch_memory,
        tile_memory,
    )
    from tasks.svd import Sketch

    src = shapes[params.store]
    nv, nl, ny, nx, nc = src.radiance
    m, n = nv * nl * nc, ny * nx
    extra = min(params.extra, min(m, n) - params.rank)
    width = params.rank + extra
    side = params.side(m, n)
    iterations = params.iterations(side)
    matrix = m * n * 4
    tile = (min(src.chunk, ny), min(src.chunk, nx))
    texels = tile[0] * tile[1]
    tile_rows = plan_tile_rows(src.radiance, src.dir_chunk, tile)
    tiles = math.ceil(ny / tile[0]) * math.ceil(nx / tile[1])
    note = f"sketches on the {side} side"
    if params.one_pass:
        sketch = Sketch.for_rank(params.rank, extra, m)
        passes = reads = 1 + params.verify
        tasks = tiles
        memory = sketch_memory(m, texels, sketch, tile_rows, workers=1)
        task, client = memory["task"], memory["client"]
        note = (f"one view (k = {sketch.k}, s = {sketch.s}) by texel tiles; scratch "
                f"{_size(n * sketch.s * 4)} written once, read once")
        option = "--oversample (a smaller sketch: less memory per task, more error)"
    elif side == "rows":
        rows = tile_rows
        cache = params.tile_cache_bytes
        twice = m * texels * 4 > cache  # a tile's column read twice per pass
        passes = iterations + 2 + params.verify
        reads = (iterations + 1) * (2 if twice else 1) + 1 + params.verify
        tasks = tiles
        task = tile_memory(m, texels, width, rows, cache=cache)
        client = 8 * 6 * m * width + FAN_IN * 8 * m * width
        if twice:  # each pass would read once if a tile's column were kept
            note += (f"; {reads} reads: a tile's column ({_size(m * texels * 4)}) exceeds "
                     f"--tile-cache ({_size(cache)}); --tile-cache "
                     f"{math.ceil(m * texels * 4 / 2**30)}GiB would keep it: "
                     f"{iterations + 2 + params.verify} reads")
        option = ("--rank, --tile-cache, or the source's --chunk (smaller texel tiles: each "
                  "task holds a tile's rows)")
    else:
        blocks = plan_row_blocks(src.radiance, src.dir_chunk)
        passes = reads = iterations + 1 + params.verify
        tasks = len(blocks)
        memory = memory_estimate(src.radiance, blocks, rank=params.rank, extra=extra,
                                 workers=1)
        task, client = memory["task"], memory["client"]
        option = "--sketch rows (client memory then grows with the rows only)"
    per_core, source = rate("compress_bytes_per_core_second")
    seconds = reads * matrix / per_core
    if params.one_pass:  # its own rate (sparse sketches: about the same work per value at any
        one, source = rate("compress_one_pass_bytes_per_core_second")  # k, s), or one read
        seconds = max(matrix / per_core, matrix / one) + params.verify * matrix / per_core
    plan = StagePlan("compress", "", read=reads * matrix, written=(m + n + 1) * params.rank * 4,
                     tasks=tasks * passes, passes=passes, reads=reads, task_bytes=task,
                     client_bytes=client, core_seconds=seconds, rate_source=source,
                     option=option, note=note)
    if alternative:  # the other mode: one pass (texel side), or the default passes
        other = dataclasses.replace(params, passes="auto" if params.one_pass else "1",
                                    sketch="auto" if params.one_pass else "texels",
                                    power_iters=None, oversample=None)
        plan.alternatives = [_compress(other, shapes, alternative=False)[0]]
        plan.alternatives[0].name = ("compress (default passes)" if params.one_pass else
                                     "compress --passes 1")
    return plan, Shape("compressed", src.radiance, src.chunk, src.dir_chunk, rank=params.rank,
                       unit=src.chunk)


def _quilt(params, shapes: dict) -> tuple[StagePlan, Shape]:
    from tasks.canvas import TERMS

    src = shapes[params.store]
    nv, nl, ny, nx, nc = src.radiance
    block = params.block or 32
    overlap = params.overlap if params.overlap is not None else block // 4
    th, tw = params.tile_shape((ny, nx), block - overlap)
    tiles = params.corners**4
    values = src.rank if src.kind == "compressed" else nv * nl * nc
    out = tiles * th * tw * values * 4
    # planning compares every tile position with every sample position: measured time grows
    # with their product (16 tiles of 1008^2 on a 1024^2 sample: 14.5 min, estimated 16.9)
    plan_seconds, source = rate("quilt_plan_seconds_per_texel_pair")
    per_core, _ = rate("quilt_values_per_core_second")
    side = src.side
    spatial = math.ceil(th / side) * math.ceil(tw / side)
    groups = 1 if src.kind == "compressed" else max(1, math.ceil(nl / src.dir_chunk)) * nv
    plan = StagePlan("quilt", "", read=ny * nx * 3 * 4 + out, written=out,
                     tasks=tiles * spatial * groups, passes=1, reads=1,
                     task_bytes=3 * side * side * min(values, src.dir_chunk * nc) * 4
                     + th * tw * TERMS * 8,
                     client_bytes=ny * nx * 3 * 4 * 4 + tiles * th * tw * TERMS * 8,
                     core_seconds=tiles * th * tw * values / per_core,
                     serial_seconds=tiles * th * tw * ny * nx * plan_seconds,
                     rate_source=source,
                     option="--size (smaller tiles)",
                     note=f"{tiles} tile(s) of {th} x {tw}"
                     + (", compressed: V only" if src.kind == "compressed" else ""))
    kind = "compressed-tileset" if src.kind == "compressed" else "tileset"
    return plan, Shape(kind, (), 0, 0)


def _crop(params, shapes: dict) -> tuple[StagePlan, Shape]:
    src = shapes[params.store]
    nv, nl, ny, nx, nc = src.radiance
    if params.region is not None:
        from pipeline.params import parse_region

        ys, xs = parse_region(params.region)
        ny, nx = ys.stop - ys.start, xs.stop - xs.start
    nv = len(set(params.view)) if params.view else nv
    nl = len(set(params.light)) if params.light else nl
    size = nv * nl * ny * nx * nc * 4
    truth = ny * nx * 6 * 4 if src.truth else 0  # height, albedo (3), roughness, specular
    chunk = params.chunk or src.chunk
    dir_chunk = params.dir_chunk or src.dir_chunk
    side = _task_side(chunk)
    per_core, source = rate("compress_bytes_per_core_second")  # a read-and-write pass
    plan = StagePlan("crop", "", read=size + truth, written=size + truth,
                     tasks=max(1, size // (side * side * dir_chunk * nc * 4)), passes=1, reads=1,
                     task_bytes=2 * max(side, src.side) ** 2 * dir_chunk * nc * 4,
                     core_seconds=size / per_core, rate_source=source, option="--chunk")
    return plan, Shape(src.kind, (nv, nl, ny, nx, nc), chunk, dir_chunk, unit=chunk,
                       truth=src.truth)


ESTIMATORS = {"generate": _generate, "compress": _compress, "quilt": _quilt, "crop": _crop}


def plan_stages(stages, shapes: dict | None = None) -> list[StagePlan]:
    """The estimates of a validated config's stages (``pipeline.config.PlannedStage``).

    ``shapes`` (a dict, filled in) receives the shape of every input and planned output.
    """
    from pipeline.params import paths

    shapes = {} if shapes is None else shapes
    out = []
    for step in stages:
        for p in paths(step.params, "in"):
            if p not in shapes and (found := shape_of(p)) is not None:
                shapes[p] = found
        estimate = ESTIMATORS.get(step.name)
        if step.name == "generate" and step.params.albedo is not None:
            estimate = None  # the size comes from the photo
        inputs_known = all(p in shapes for p in paths(step.params, "in"))
        if estimate is None or not inputs_known or not _radiance_known(step, shapes):
            plan = StagePlan(step.name, step.where, note="no estimate: " + (
                "its cost depends on the data" if estimate is None else
                "its input's shape is not known before it runs"))
        else:
            plan, made = estimate(step.params, shapes)
            plan.where = step.where
            for p in paths(step.params, "out"):
                shapes[p] = made
        out.append(plan)
    return out


def chunks_of(shape: Shape) -> int | None:
    """Stored chunks of a store's main arrays (radiance; U and V of a compressed store)."""
    if not shape.radiance or not shape.chunk:
        return None
    nv, nl, ny, nx, _ = shape.radiance
    spatial = math.ceil(ny / shape.chunk) * math.ceil(nx / shape.chunk)
    if shape.kind == "compressed":
        return spatial + nv * math.ceil(nl / shape.dir_chunk)
    return nv * math.ceil(nl / shape.dir_chunk) * spatial


def planned_directions(stages, path: str):
    """Directions of an existing store, or of one a stage of ``stages`` makes (None: unknown).

    Follows the stages that keep their input's directions back to a store or a ``generate``.
    """
    from pipeline.params import names_path
    from pipeline.stores.base import Directions, open_group, read_directions
    from tasks.sampling import parse_sampling

    for step in reversed(stages):
        if not names_path(step.params, "out", path):
            continue
        p = step.params
        if step.name == "generate":
            s = parse_sampling(p.sampling)
            return Directions(s.theta_view, s.phi_view, s.theta_light, s.phi_light)
        if step.name in ("compress", "quilt", "reconstruct", "crop", "pyramid", "roller"):
            d = planned_directions(stages, p.store)
            if d is None or step.name not in ("reconstruct", "crop"):
                return d
            return d.select(p.view or range(d.views), p.light or range(d.lights))
        return None
    try:
        return read_directions(open_group(path))
    except BTFError:
        return None


def _radiance_known(step, shapes) -> bool:
    from pipeline.params import paths

    return all(shapes[p].radiance for p in paths(step.params, "in") if p in shapes)


def worker_limit(options, client=None) -> tuple[int, int, str]:
    """``(bytes per worker, threads per worker, what says so)`` for the session's workers."""
    if client is not None:
        info = client.scheduler_info()["workers"]
        if info:
            limit = min(w.get("memory_limit") or 0 for w in info.values())
            threads = max(w.get("nthreads", 1) for w in info.values())
            if limit:
                return limit, threads, f"the cluster's smallest worker ({len(info)} workers)"
    import psutil

    total = psutil.virtual_memory().total
    workers = options.workers or (os.cpu_count() or 1) + 1
    if options.scheduler == "processes":
        return total // workers, 1, f"this machine's memory over {workers} processes"
    return total, workers, f"this machine's memory ({workers} worker threads in one process)"


def check_memory(plans: list[StagePlan], limit: int, threads: int, source: str,
                 available: int) -> None:
    """Refuse a plan whose workers or client would need more memory than they have."""
    for p in plans:
        if not p.task_bytes and not p.client_bytes:
            continue
        worker = BASE_PROCESS + threads * p.task_bytes
        if worker > limit:
            raise BTFError(f"{p.where}: needs ~{worker / GiB:.1f} GiB per worker ({threads} "
                           f"task(s) of {p.task_bytes / GiB:.2f} GiB), more than {source} "
                           f"allows ({limit / GiB:.1f} GiB); change {p.option}")
        if p.client_bytes > available:
            raise BTFError(f"{p.where}: the client needs ~{p.client_bytes / GiB:.1f} GiB, more "
                           f"than this machine's {available / GiB:.1f} GiB available; change "
                           f"{p.option}")


def _size(n: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n / 1e3:.0f} kB"


def report(plans: list[StagePlan], *, cores: int, limit: int, threads: int,
           source: str) -> str:
    """The plan as a table, with totals and the cores that finish it in an hour."""
    lines = ["| stage | read | written | tasks | passes | per task | client | est. time "
             f"({cores} cores) | notes |", "|---|---|---|---|---|---|---|---|---|"]
    total = serial = 0.0
    sources = set()
    for p in plans:
        if p.core_seconds is None:
            lines.append(f"| {p.name} | | | | | | | | {p.note} |")
            continue
        total += p.core_seconds
        serial += p.serial_seconds
        sources.add(p.rate_source)
        lines.append(_row(p, p.name, p.note, cores))
        lines += [_row(a, f"*instead: {a.name}*", f"{a.note}; not in the totals", cores)
                  for a in p.alternatives if a.core_seconds is not None]
    hour = (f"{math.ceil(total / (3600 - serial))} cores finish it in an hour if it scales "
            "linearly" if serial < 3600 else "the client's serial part alone takes over an hour")
    lines += ["", f"Estimated: {_duration(serial + total / cores)} on {cores} cores "
              f"({total / 3600:.1f} core-hours in tasks, {_duration(serial)} on the client; "
              f"{hour}). Rates: {'; '.join(sorted(sources)) or '-'}.",
              f"Memory: each worker {threads} task(s) at a time, limit "
              f"{limit / GiB:.1f} GiB ({source})."]
    return "\n".join(lines)


def _row(p: StagePlan, name: str, note: str, cores: int) -> str:
    passes = f"{p.passes} ({p.reads} reads)" if p.reads > p.passes else str(p.passes)
    return (f"| {name} | {_size(p.read)} | {_size(p.written)} | {p.tasks} | {passes} | "
            f"{_size(p.task_bytes)} | {_size(p.client_bytes)} | "
            f"{_duration(p.serial_seconds + p.core_seconds / cores)} | {note} |")


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    if seconds >= 60:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.1f} s"


def plan_record(plans: list[StagePlan]) -> list[dict[str, Any]]:
    """The plan as JSON-ready records."""
    return [dataclasses.asdict(p) for p in plans]
