"""Chunk checksums: a changed byte is found on read and named; older stores stay readable."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

from helpers import generate_store
from pipeline.atomic import consolidate

GEN = ("--material", "wood", "--size", "32", "--sampling", "hemi:4", "--chunk", "16",
       "--dir-chunk", "2", "--seed", "4")


def _chunk_files(store: Path) -> list[Path]:
    return sorted(p for p in (store / "radiance" / "c").rglob("*") if p.is_file())


def _flip(path: Path, at: float = 0.5) -> None:
    data = bytearray(path.read_bytes())
    data[int(len(data) * at)] ^= 0x10
    path.write_bytes(bytes(data))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _grid_index(store: Path, path: Path) -> tuple[int, ...]:
    return tuple(int(p) for p in path.relative_to(store / "radiance" / "c").parts)


@pytest.mark.parametrize("damage", [_flip, _truncate])
def test_a_changed_chunk_is_named_by_every_reader_and_nothing_is_written(tmp_path, btf,
                                                                         damage):
    store = generate_store(tmp_path / "g.zarr", *GEN, "--shard", "0")
    files = _chunk_files(store)
    rng = np.random.default_rng(len(files))
    bad = sorted(files[i] for i in rng.choice(len(files), 2, replace=False))
    for path in bad:
        damage(path)
    scanned = btf("inspect", store, "--scan")
    assert scanned.code == 1
    listed = [line.split()[1:] for line in scanned.err.splitlines()
              if line.startswith("  radiance ")]
    want = [_grid_index(store, p) for p in bad]
    found = [tuple(int(v) for v in " ".join(w).split(")")[0].strip("(").split(", "))
             for w in listed]
    assert found == want, scanned.err  # exactly the damaged chunks, in order
    assert "2 chunk(s) fail their checksum" in scanned.err
    compressed = btf("compress", store, tmp_path / "c.zarr", "--rank", "4")
    assert compressed.code == 1 and f"{store}: variable 'radiance', chunk " in compressed.err
    assert any(str(w) in compressed.err for w in want) and "bytes changed" in compressed.err
    assert not (tmp_path / "c.zarr").exists()
    cropped = btf("crop", store, tmp_path / "r.zarr", "--region", "0:32,0:32")
    assert cropped.code == 1 and "fails its checksum" in cropped.err
    assert "btf inspect STORE --scan" in cropped.err and "Traceback" not in cropped.err
    assert not (tmp_path / "r.zarr").exists()


def test_a_damaged_shard_is_found(tmp_path, btf):
    store = generate_store(tmp_path / "s.zarr", *GEN, "--shard", "32")
    (shard,) = [p for p in _chunk_files(store) if _grid_index(store, p)[:2] == (1, 0)]
    for at in (0.3, 0.999):  # an inner chunk, then the shard's index at its end
        original = shard.read_bytes()
        _flip(shard, at)
        scanned = btf("inspect", store, "--scan")
        assert scanned.code == 1 and "checksum" in scanned.err, scanned.err
        shard.write_bytes(original)
    assert btf("inspect", store, "--scan").code == 0


def test_stores_written_before_checksums_read_as_they_did(tmp_path, btf):
    new = generate_store(tmp_path / "new.zarr", *GEN)
    old = generate_store(tmp_path / "old.zarr", *GEN)
    group = zarr.open_group(old, mode="r+", use_consolidated=False)
    values, attrs = group["radiance"][...], dict(group["radiance"].attrs)
    blosc, _ = group["radiance"].compressors
    chunks, dims = group["radiance"].chunks, group["radiance"].metadata.dimension_names
    del group["radiance"]
    group.create_array("radiance", shape=values.shape, chunks=chunks, dtype=values.dtype,
                       compressors=(blosc,), dimension_names=dims, attributes=attrs)[...] = values
    consolidate(old)
    assert [c.to_dict()["name"] for c in zarr.open_group(old)["radiance"].compressors] == \
        ["blosc"]
    assert btf("inspect", old, "--scan").code == 0
    for store in (new, old):
        assert btf("compress", store, tmp_path / f"{store.stem}_svd.zarr", "--rank", "4").code == 0
    a, b = (zarr.open_group(tmp_path / f"{n}_svd.zarr", mode="r") for n in ("new", "old"))
    for name in ("U", "S", "V"):
        assert np.array_equal(a[name][...], b[name][...]), name


@pytest.mark.slow
def test_btf_bench_checksums_measures_both_codecs():
    import argparse

    from benchmarks import checksums as suite

    result = suite.run(argparse.Namespace(size=64, repeat=1))
    for key in ("write_seconds", "read_seconds"):
        assert set(result[key]) == {"blosc", "blosc + crc32c"}
        assert all(v > 0 for v in result[key].values())
    assert result["bytes"] == 64 * 64 * 48 * 3 * 4 and result["stored_bytes"] > 0
    text = suite.report(result)
    assert "| blosc + crc32c |" in text and "| blosc | " in text
