"""``btf bench mitsuba --quick`` end to end (slow; needs Mitsuba 3 and its llvm variant)."""

from __future__ import annotations

import os

import pytest

pytestmark = pytest.mark.slow


def test_bench_mitsuba_quick_times_and_sweeps_btfs_bsdf(tmp_path, capsys):
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        if os.environ.get("BTF_REQUIRE_MITSUBA") == "1":
            raise
        pytest.skip("Mitsuba 3 is not installed (pip install 'btf-pipeline[mitsuba]')")
    from pipeline import mitsuba_plugin

    if not mitsuba_plugin.llvm_works(mitsuba_plugin.llvm_library()):
        if os.environ.get("BTF_REQUIRE_MITSUBA") == "1":
            raise RuntimeError("Mitsuba's llvm variant does not run: LLVM 16 or later needed")
        pytest.skip("Mitsuba's llvm variant needs LLVM 16 or later")
    from benchmarks.cli import main

    out = tmp_path / "m.json"
    assert main(["mitsuba", "--quick", "--workdir", str(tmp_path), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| btf BSDF (Dr.Jit) |" in text and "no --peer checkout" in text
    import json

    result = json.loads(out.read_text())["btf"]
    assert result["frame_s"] > 0 and result["peak_rss"] > 0
    # the sweep crosses measured lights (theta 15 of the 9-light quick zip): the image changes
    # at every step, and by a small amount (the blend is continuous)
    assert 0 < result["median_step"] <= result["largest_step"] < 0.5
    assert list(tmp_path.iterdir()) == [out]  # its stores are removed
