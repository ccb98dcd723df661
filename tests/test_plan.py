"""``btf run --plan``: estimates before anything runs, checked against runs and arithmetic."""

from __future__ import annotations

from pathlib import Path

import pytest
import zarr

from pipeline import planning
from pipeline.config import load
from pipeline.errors import BTFError

ROOT = Path(__file__).resolve().parents[1]
TERABYTE = ROOT / "configs" / "terabyte.yaml"


def _nbytes(path: Path, names) -> int:
    g = zarr.open_group(path, mode="r")
    return sum(g[n].nbytes for n in names)


def test_the_terabyte_plan_is_what_the_arithmetic_says(tmp_path, btf, monkeypatch):
    monkeypatch.setenv("BTF_RATES", str(tmp_path / "rates.json"))
    plans = planning.plan_stages(load(TERABYTE).stages)
    generate, compress, quilt = plans
    rows, texels = 151 * 151 * 3, 2048 * 2048  # dome151 x RGB, 2048^2
    assert generate.bytes_written == rows * texels * 4 + texels * 6 * 4  # radiance and the truth
    # each worker process keeps its shadow and view caches: counted once
    from tasks.shading import SHADOWS, VIEWS

    assert generate.process_bytes == SHADOWS.limit + VIEWS.limit
    worker = planning.BASE_PROCESS + SHADOWS.limit + VIEWS.limit + 2 * generate.task_bytes
    planning.check_memory([generate], worker, 2, "x", available=1 << 40)
    with pytest.raises(BTFError, match=r"needs ~.* GiB per worker \(2 task\(s\) of .* GiB and "
                                       r"134\.2 MB kept\)"):
        planning.check_memory([generate], worker - 1, 2, "x", available=1 << 40)
    # the texel side would need 15 GB; the note says how to read less
    assert compress.note == ("sketches on the rows side; 7 reads: a tile's column (4.5 GB) "
                             "exceeds --tile-cache (268.4 MB); --tile-cache 5GiB would keep "
                             "it: 4 reads")
    kept = planning.plan_stages(load(TERABYTE, ("compress.tile_cache=5GiB",)).stages)[1]
    assert kept.input_reads == kept.passes == 4 and kept.bytes_read == 4 * rows * texels * 4
    assert rows * 128 * 128 * 4 < kept.task_bytes < 5 << 30
    # rows side: 2 power passes and the projection read each tile's column twice (68403 rows
    # x 128^2 texels do not fit the cache), then the V pass: 7 reads of the 1.1 TB matrix
    assert compress.passes == 4 and compress.input_reads == 7
    assert compress.bytes_read == 7 * rows * texels * 4
    assert compress.client_bytes < 1 << 30 and compress.task_bytes < 1 << 30
    # the other mode is shown beside it: one read of the matrix by texel tiles, the client
    # holding rows x k (k = 6 x 64 + 1 = 385), each task a tile's co-range sketch (s = 771)
    (one,) = compress.alternatives
    assert one.name == "compress --passes 1" and one.passes == one.input_reads == 1
    assert one.bytes_read == rows * texels * 4
    assert rows * 385 * 8 * 3 < one.client_bytes < 1e9
    assert 771 * 128 * 128 * 4 * 2 < one.task_bytes < 1 << 30
    assert f"scratch {planning.human_bytes(texels * 771 * 4)} written once" in one.note
    assert "16 tile(s)" in quilt.note and quilt.serial_seconds > 0
    result = btf("run", TERABYTE, "--plan", "--memory-limit", "4GiB")
    assert result.code == 0, result.err
    assert "| compress | 8.0 TB | 1.1 GB | 1024 | 4 (7 reads) |" in result.out
    assert "| *instead: compress --passes 1* | 1.1 TB | 1.1 GB |" in result.out
    assert "not in the totals" in result.out
    assert "cores finish it in an hour" in result.out
    assert not (ROOT / "out" / "terabyte").exists()


def test_a_plan_over_the_workers_memory_is_refused_naming_stage_and_option(btf):
    result = btf("run", TERABYTE, "--plan", "--memory-limit", "1GiB")
    assert result.code == 1
    line = TERABYTE.read_text().splitlines().index("  - compress:") + 1
    assert f"terabyte.yaml:{line}: stages[1].compress: needs ~" in result.err
    assert "more than --memory-limit allows (1.0 GiB); change --rank" in result.err
    texel_side = planning.plan_stages(load(TERABYTE, ("compress.sketch=texels",)).stages)[1]
    assert texel_side.client_bytes > 14e9  # 6 float64 sketches of 4.2 M texels x 74
    with pytest.raises(BTFError, match=r"the client needs ~.* change --sketch rows"):
        planning.check_memory([texel_side], 8 << 30, 2, "x", available=8 << 30)
    assert btf("run", TERABYTE, "--plan", "--memory-limit", "lots").code == 2


def test_estimated_bytes_match_a_real_run_and_a_refused_run_writes_nothing(tmp_path, btf):
    config = tmp_path / "small.yaml"
    out = tmp_path / "out"
    config.write_text(f"""stages:
  - generate: {{out: {out}/s.zarr, material: wood, size: 96, sampling: "abtf:6,2", chunk: 32}}
  - crop: {{store: {out}/s.zarr, out: {out}/c.zarr, region: "8:72,0:64", light: [0, 3]}}
  - compress: {{store: {out}/s.zarr, out: {out}/k.zarr, rank: 8}}
""")
    refused = btf("run", config, "--memory-limit", "310MiB", "--quiet")
    assert refused.code == 1 and "stages[0].generate: needs" in refused.err
    assert not out.exists()  # refused before anything ran
    plans = planning.plan_stages(load(config).stages)
    assert btf("run", config, "--quiet").code == 0
    generate, crop, compress = plans
    truth = ("radiance", "height", "albedo", "roughness", "specular")
    assert generate.bytes_written == _nbytes(out / "s.zarr", truth)
    assert crop.bytes_written == _nbytes(out / "c.zarr", truth)
    assert compress.bytes_written == _nbytes(out / "k.zarr", ("U", "S", "V"))
    k = zarr.open_group(out / "k.zarr", mode="r").attrs["svd"]
    assert compress.passes == k["passes"] and compress.note.endswith(k["sketch_side"] + " side")
    big, sharded = (planning.plan_stages(load(config, ("generate.size=4096", *extra)).stages)[0]
                    for extra in ((), ("generate.shard=1024",)))
    # a task block is made of whole shards: 1024^2 texels instead of 512^2
    assert 3.5 < sharded.task_bytes / big.task_bytes < 4.0


def test_rates_measured_by_bench_replace_the_built_in_ones(tmp_path, monkeypatch):
    monkeypatch.setenv("BTF_RATES", str(tmp_path / "rates.json"))
    key = "compress_bytes_per_core_second"
    assert planning.rate(key) == (planning.BUILT_IN_RATES[key], "built-in (the test machine's)")
    planning.record_rates({key: 1e9}, "compress")
    value, source = planning.rate(key)
    assert value == 1e9 and source.startswith("measured by btf bench compress")
    plan = planning.plan_stages(load(TERABYTE).stages)[1]
    assert plan.core_seconds == pytest.approx(plan.bytes_read / 1e9)
