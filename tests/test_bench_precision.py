"""``btf bench precision --quick``: float16 against float32 side by side, end to end."""

from __future__ import annotations

import argparse
import os

import pytest


def _cgroups_writable() -> bool:
    from benchmarks.precision import CGROUP_ROOT

    return os.geteuid() == 0 and os.access(CGROUP_ROOT, os.W_OK)


@pytest.mark.slow  # a 9 x 9 zip ingested four times, two view pages and two scenes (~30 s)
def test_btf_bench_precision_quick_measures_both_precisions(tmp_path):
    from benchmarks import precision as suite

    # the compress part needs root and a writable cgroup v1 memory hierarchy; its store is
    # tiny here (it fits the limit: the report says so)
    compress = _cgroups_writable()
    parser = argparse.ArgumentParser()
    suite.add_arguments(parser)
    args = parser.parse_args(["--quick", "--parts",
                              "ingest,view" + (",compress" if compress else ""),
                              "--gigabytes", "0.01", "--compress-size", "32", "--rank", "4",
                              "--workdir", str(tmp_path)])
    result = suite.run(args)
    assert list(tmp_path.iterdir()) == []  # temporary stores removed

    ingest = result["ingest"]
    assert ingest["images"] == 81 and ingest["decode_1_per_s"] > 0
    assert [r["dtype"] for r in ingest["runs"]] == ["float16", "float32"] * 2
    assert all(r["seconds"] > 0 and r["per_s"] > 0 for r in ingest["runs"])
    assert ingest["stored_dtype"] == {"float16": "float16", "float32": "float32"}
    assert ingest["store_bytes"]["float16"] < ingest["store_bytes"]["float32"]
    assert ingest["rounded"]["equal"] and ingest["rounded"]["values"] > 0

    view = result["view"]
    assert view["rounded"]["equal"]
    assert set(view["pages"]) == set(view["scenes"]) == {"float32", "float16"}
    assert all(p["page_bytes"] > 0 and p["seconds"] > 0 for p in view["pages"].values())
    assert 0 < view["scene_rel_rms"] < 2**-10 and 0 <= view["scene_max_abs"] < 1e-2

    text = suite.report(result)
    assert text.count("| float16 (float16) | ") == 2 and text.count("| float32 (float32) | ") == 2
    assert "The float16 store equals the float32 store rounded to float16" in text
    assert "does NOT equal" not in text
    assert "| float32 | " in text and "| float16 | " in text and "relative RMS" in text

    if compress:
        c = result["compress"]
        assert c["cgroup"] and c["limit"] == 1 << 30 and c["rounded"]["equal"]
        assert [(r["dtype"], r["mode"], r["passes"]) for r in c["runs"]] == [
            ("float32", "default", 3), ("float16", "default", 3),
            ("float32", "one pass", 1), ("float16", "one pass", 1)]
        assert all(r["read_bytes"] >= 0 and 0 < r["error"] < 1 for r in c["runs"])
        assert c["s_difference"]["default"] < 1e-3
        assert "| float16 | one pass | 1 | " in text and "NOT more than that room" in text
        assert not (suite.CGROUP_ROOT / f"btfbench_{os.getpid()}").exists()
