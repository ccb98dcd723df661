"""``btf run --plan``: what each stage of a config will read, write and hold, before it runs.

Per stage: the bytes read and written (float32 values, before compression), the tasks, the
passes over its input, the peak memory of one task and of the client, and an estimated time
from rates measured on this machine by ``btf bench`` (stored in :func:`rates_path`; built-in
rates, measured on the project's 2-core test machine and listed in BENCHMARKS.md, stand in for
suites not yet run here). Shapes come from the input stores' metadata, or from the plan of the
earlier stage that makes them: nothing is read or computed. Each stage estimates itself (its
declaration's ``estimate``, :class:`pipeline.stage.Stage`, with :class:`StageEstimate`,
:class:`Shape` and :func:`rate` from here); this module is the engine and imports no stage.

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

from pipeline.errors import BTFError

GiB = 1 << 30
BASE_PROCESS = 300 << 20  # interpreter, numpy, dask, zarr: a worker's memory before any task
BUILT_IN_RATES = {  # per core, btf bench on the 2-core test VM (BENCHMARKS.md, "The terabyte plan")
    "generate_texel_directions_per_core_second": 6.2e6,
    "generate_path_samples_per_core_second": 1.6e6,
    "compress_bytes_per_core_second": 0.37e9,
    # --passes 1 (K = 64: k = 385, s = 771, sparse sign maps; 30603 x 65536, 8 GB), with the
    # compiled sign products, 32 MiB blocks and the untransposed scratch (BENCHMARKS.md, "The
    # one pass's products compiled")
    "compress_one_pass_bytes_per_core_second": 0.19e9,
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
    itemsize: int = 4  # bytes per stored value of radiance (float16: 2), or of V

    @property
    def side(self) -> int:
        """Texels per side of a task block (as :func:`pipeline.graphs.blocks.task_block`)."""
        from pipeline.graphs.blocks import task_side

        return task_side(self.unit or self.chunk)


@dataclasses.dataclass
class StageEstimate:
    """The estimate of one stage."""

    name: str
    where: str
    bytes_read: int = 0
    bytes_written: int = 0
    tasks: int = 0
    passes: int = 0
    input_reads: int = 0  # reads of the input (a pass may read it twice)
    task_bytes: int = 0
    process_bytes: int = 0  # kept by each worker process across its tasks (generate's shadows)
    client_bytes: int = 0
    core_seconds: float | None = None  # work that parallelises over the workers' cores
    serial_seconds: float = 0.0  # work on the client alone (quilt planning)
    rate_source: str = ""
    option: str = ""
    note: str = ""
    # the same stage in its other mode (compress: one pass or several), for the user to compare
    alternatives: list[StageEstimate] = dataclasses.field(default_factory=list)


def shape_of(path: str) -> Shape | None:
    """The shape of an existing store from its metadata (None if it is no store btf knows)."""
    from pipeline.stores import CompressedStore, RadianceStore, open_store

    try:
        store = open_store(path, checked=False)
    except BTFError:
        return None
    if isinstance(store, RadianceStore) and store.has("radiance"):
        layout = store.layout
        return Shape(store.directions.kind, store.shape, layout.chunk, layout.dir_chunk,
                     unit=layout.shard or layout.chunk, truth=store.has("height"),
                     itemsize=layout.itemsize)
    if isinstance(store, CompressedStore):
        return Shape("compressed", store.shape, store["V"].chunks[0], store["U"].chunks[1],
                     rank=store.rank, itemsize=store["V"].dtype.itemsize)
    return Shape(str(store.kind), (), 0, 0)


def plan_stages(stages, shapes: dict | None = None) -> list[StageEstimate]:
    """The estimates of a validated config's stages (``pipeline.config.PlannedStage``).

    Each stage estimates itself (its declaration's ``estimate``, :class:`pipeline.stage.Stage`)
    from the shapes of its inputs. ``shapes`` (a dict, filled in) receives the shape of every
    input and planned output.
    """
    from pipeline.params import paths

    shapes = {} if shapes is None else shapes
    out = []
    for step in stages:
        for p in paths(step.params, "in"):
            if p not in shapes and (found := shape_of(p)) is not None:
                shapes[p] = found
        estimate, result, why = step.stage.estimate, None, "its cost depends on the data"
        if estimate is not None and not _inputs_known(step, shapes):
            why = "its input's shape is not known before it runs"
        elif estimate is not None:
            result = estimate(step.params, shapes)
        if result is None:
            plan = StageEstimate(step.name, step.where, note=f"no estimate: {why}")
        else:
            plan, made = result
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

    Follows the stages' declared ``directions`` back to a store, or to a stage that makes
    its own (``generate``).
    """
    from pipeline.params import names_path
    from pipeline.stores import open_store

    for step in reversed(stages):
        if not names_path(step.params, "out", path):
            continue
        derive = step.stage.directions
        if derive is None:
            return None
        store = getattr(step.params, "store", None)
        return derive(step.params, None if store is None else planned_directions(stages, store))
    try:
        return open_store(path, checked=False).directions
    except BTFError:
        return None


def _inputs_known(step, shapes) -> bool:
    """Whether the shapes (and radiance shapes) of all of a stage's inputs are known."""
    from pipeline.params import paths

    inputs = paths(step.params, "in")
    return all(p in shapes and shapes[p].radiance for p in inputs)


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
    workers = options.local_workers(reads=True)
    if options.scheduler == "processes":
        return total // workers, 1, f"this machine's memory over {workers} processes"
    return total, workers, f"this machine's memory ({workers} worker threads in one process)"


def check_memory(plans: list[StageEstimate], limit: int, threads: int, source: str,
                 available: int) -> None:
    """Refuse a plan whose workers or client would need more memory than they have."""
    for p in plans:
        if not (p.task_bytes or p.process_bytes or p.client_bytes):
            continue
        worker = BASE_PROCESS + p.process_bytes + threads * p.task_bytes
        if worker > limit:
            kept = f" and {human_bytes(p.process_bytes)} kept" if p.process_bytes else ""
            raise BTFError(f"{p.where}: needs ~{worker / GiB:.1f} GiB per worker ({threads} "
                           f"task(s) of {p.task_bytes / GiB:.2f} GiB{kept}), more than {source} "
                           f"allows ({limit / GiB:.1f} GiB); change {p.option}")
        if p.client_bytes > available:
            raise BTFError(f"{p.where}: the client needs ~{p.client_bytes / GiB:.1f} GiB, more "
                           f"than this machine's {available / GiB:.1f} GiB available; change "
                           f"{p.option}")


def human_bytes(n: float) -> str:
    """``n`` bytes in kB, MB, GB or TB, one decimal."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n / 1e3:.0f} kB"


def report(plans: list[StageEstimate], *, cores: int, limit: int, threads: int,
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


def _row(p: StageEstimate, name: str, note: str, cores: int) -> str:
    passes = (f"{p.passes} ({p.input_reads} reads)" if p.input_reads > p.passes
              else str(p.passes))
    kept = f" (+ {human_bytes(p.process_bytes)} a process)" if p.process_bytes else ""
    return (f"| {name} | {human_bytes(p.bytes_read)} | {human_bytes(p.bytes_written)} | "
            f"{p.tasks} | {passes} | "
            f"{human_bytes(p.task_bytes)}{kept} | {human_bytes(p.client_bytes)} | "
            f"{_duration(p.serial_seconds + p.core_seconds / cores)} | {note} |")


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    if seconds >= 60:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.1f} s"
