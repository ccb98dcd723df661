"""``btf compress``: out-of-core randomized SVD of a store (paper 000, section 2.1).

The stage declares its parameters, help and estimate; :mod:`pipeline.compression` computes.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from pipeline.compression import CompressSettings, peak_memory
from pipeline.compression import compress as compress_store
from pipeline.graphs.row_passes import plan_row_blocks
from pipeline.planning import Shape, StageEstimate, human_bytes, rate
from pipeline.session import Session
from pipeline.stage import Stage, same_directions
from tasks.svd import Sketch


@dataclasses.dataclass(frozen=True)
class CompressParams(CompressSettings):
    """Parameters of ``btf compress``."""


def compress(params: CompressParams, session: Session) -> Path:
    """Compress the store of ``params`` into U, S, V; returns the output path."""
    return compress_store(params, session)


def _estimate(params: CompressParams, shapes: dict, *,
              alternative: bool = True) -> tuple[StageEstimate, Shape]:
    """``btf run --plan``'s estimate, with the other mode (one pass or several) beside it."""
    src = shapes[params.store]
    nv, nl, ny, nx, nc = src.radiance
    # bytes of a stored V value: as asked, else a compressed input's own, else float32's
    v_size = ({"float16": 2, "float32": 4}[params.v_dtype] if params.v_dtype
              else src.itemsize if src.kind == "compressed" else 4)
    if src.kind == "compressed":  # its factors: V read twice, U held, V written
        k, rank = src.rank or params.rank, min(params.rank, src.rank or params.rank)
        v_bytes, u_bytes = ny * nx * k * src.itemsize, nv * nl * nc * k * 8
        per_core, source = rate("compress_bytes_per_core_second")
        plan = StageEstimate("compress", "", bytes_read=2 * v_bytes + u_bytes // 2,
                             bytes_written=(nv * nl * nc + 1) * rank * 4 + ny * nx * rank * v_size,
                             tasks=2 * max(1, math.ceil(ny / src.chunk) * math.ceil(
                                 nx / src.chunk)), passes=2, input_reads=2,
                             task_bytes=2 * src.chunk**2 * k * 8, client_bytes=3 * u_bytes,
                             core_seconds=2 * ny * nx * k * 4 / per_core, rate_source=source,
                             option="--rank",
                             note="a compressed store: its factors truncated or re-factored")
        return plan, Shape("compressed", src.radiance, src.chunk, src.dir_chunk, rank=rank,
                           unit=src.chunk, itemsize=v_size)
    m, n = nv * nl * nc, ny * nx
    extra = min(params.extra, min(m, n) - params.rank)
    side = params.side(m, n)
    iterations = params.iterations(side)
    matrix = m * n * src.itemsize  # the store's bytes (float16: 2 a value)
    work = m * n * 4  # what a pass computes on: float32, whatever the store holds
    tile = (min(src.chunk, ny), min(src.chunk, nx))
    texels = tile[0] * tile[1]
    tiles = math.ceil(ny / tile[0]) * math.ceil(nx / tile[1])
    note = f"sketches on the {side} side"
    memory = peak_memory(params, src.radiance, src.dir_chunk, tile, workers=1)
    task, client = memory["task"], memory["client"]
    if params.one_pass:
        sketch = Sketch.for_rank(params.rank, extra, m)
        passes = reads = 1 + params.verify
        tasks = tiles
        note = (f"one view (k = {sketch.k}, s = {sketch.s}) by texel tiles; scratch "
                f"{human_bytes(n * sketch.s * 4)} written once, read once")
        option = "--oversample (a smaller sketch: less memory per task, more error)"
    elif side == "rows":
        cache = params.tile_cache_bytes
        twice = m * texels * 4 > cache  # a tile's column read twice per pass
        passes = iterations + 2 + params.verify
        reads = (iterations + 1) * (2 if twice else 1) + 1 + params.verify
        tasks = tiles
        if twice:  # each pass would read once if a tile's column were kept
            note += (f"; {reads} reads: a tile's column ({human_bytes(m * texels * 4)}) exceeds "
                     f"--tile-cache ({human_bytes(cache)}); --tile-cache "
                     f"{math.ceil(m * texels * 4 / 2**30)}GiB would keep it: "
                     f"{iterations + 2 + params.verify} reads")
        option = ("--rank, --tile-cache, or the source's --chunk (smaller texel tiles: each "
                  "task holds a tile's rows)")
    else:
        passes = reads = iterations + 1 + params.verify
        tasks = len(plan_row_blocks(src.radiance, src.dir_chunk))
        option = "--sketch rows (client memory then grows with the rows only)"
    per_core, source = rate("compress_bytes_per_core_second")
    seconds = reads * work / per_core
    if params.one_pass:  # its own rate (sparse sketches: about the same work per value at any
        one, source = rate("compress_one_pass_bytes_per_core_second")  # k, s), or one read
        seconds = max(work / per_core, work / one) + params.verify * work / per_core
    plan = StageEstimate("compress", "", bytes_read=reads * matrix,
                         bytes_written=(m + 1) * params.rank * 4 + n * params.rank * v_size,
                         tasks=tasks * passes,
                         passes=passes, input_reads=reads, task_bytes=task,
                         client_bytes=client, core_seconds=seconds, rate_source=source,
                         option=option, note=note)
    if alternative:  # the other mode: one pass (texel side), or the default passes
        other = dataclasses.replace(params, passes="auto" if params.one_pass else "1",
                                    sketch="auto" if params.one_pass else "texels",
                                    power_iters=None, oversample=None)
        plan.alternatives = [_estimate(other, shapes, alternative=False)[0]]
        plan.alternatives[0].name = ("compress (default passes)" if params.one_pass else
                                     "compress --passes 1")
    return plan, Shape("compressed", src.radiance, src.chunk, src.dir_chunk, rank=params.rank,
                       unit=src.chunk, itemsize=v_size)


STAGE = Stage("compress", CompressParams, compress,
              "out-of-core randomized SVD of a store into U, S, V",
              "Factorise the range-reduced BTF matrix log(radiance + eps) (rows: view x light x "
              "channel textures, columns: texels) as U S V^T with a randomized SVD that streams "
              "the store in row blocks: power iterations + 1 passes (each A^T A fused into one "
              "pass), or one read with --passes 1 (a one-view sketch by texel tiles, its co-range "
              "sketch kept in a scratch array that is removed at the end). The relative error "
              "comes from an exact identity (or, for one pass, an error sketch); --verify adds "
              "a pass for the average ABRDF RMSE in linear radiance. Memory: a few blocks and "
              "sketches; with --sketch rows or --passes 1 nothing grows with the texels. "
              "A compressed store (btf compress, btf ingest FILE.btf, btf enlarge) is brought "
              "to a lower --rank from its factors, keeping its transform: truncated if its U "
              "and V are orthonormal (an SVD already), else re-factored exactly first; the log "
              "says which and the share of the values dropped.",
              makes_store=True,
              estimate=_estimate, whole="the SVD needs every layer and texel",
              directions=same_directions)
