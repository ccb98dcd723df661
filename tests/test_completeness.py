"""Every chunk written and checked for at the commit; a sealed store's missing chunk is an error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import zarr
from zarr.storage import LocalStore

from helpers import generate_store
from pipeline import completeness, storage

GEN = ("--material", "wood", "--size", "32", "--sampling", "hemi:4", "--chunk", "16",
       "--dir-chunk", "2", "--seed", "4")


def _chunk_files(store: Path) -> list[Path]:
    return sorted(p for p in (store / "radiance" / "c").rglob("*") if p.is_file())


def _grid_index(store: Path, path: Path) -> tuple[int, ...]:
    return tuple(int(p) for p in path.relative_to(store / "radiance" / "c").parts)


def _listed(err: str) -> list[tuple[tuple[int, ...], bool]]:
    """The scan's listed radiance chunks: grid index and whether it says missing."""
    out = []
    for line in err.splitlines():
        if line.startswith("  radiance "):
            index = line.split("(", 1)[1].split(")", 1)[0]
            out.append((tuple(int(v) for v in index.split(", ")), line.endswith("(missing)")))
    return out


def test_chunk_keys_are_told_from_metadata_and_hidden_keys():
    assert storage.chunk_key("radiance/c/0/3/1") == ("radiance", "c/0/3/1")
    assert storage.chunk_key("level/1/V/c/2/0") == ("level/1/V", "c/2/0")
    assert storage.chunk_key("c/4") == ("", "c/4")  # an array at the root
    assert storage.chunk_key("S/c") == ("S", "c")  # a 0-d array's one chunk
    for key in ("zarr.json", "radiance/zarr.json", ".btf-done/radiance~1", "c/zarr.json",
                ".level.partial-1234/V/c/0/0", "radiance/c/x"):
        assert storage.chunk_key(key) is None, key


@pytest.mark.parametrize("shard", ["0", "32"])
def test_a_missing_chunk_is_named_by_every_reader_and_listed_by_the_scan(tmp_path, btf, shard):
    store = generate_store(tmp_path / "g.zarr", *GEN, "--shard", shard)
    assert zarr.open_group(store, mode="r").attrs[storage.SEALED] is True
    files = _chunk_files(store)
    rng = np.random.default_rng(len(files))
    gone = sorted(files[i] for i in rng.choice(len(files), 2, replace=False))
    for path in gone:
        path.unlink()
    scanned = btf("inspect", store, "--scan")
    assert scanned.code == 1, scanned.err
    listed = _listed(scanned.err)
    radiance = zarr.open_array(store, path="radiance", mode="r")
    keys = {str(p.relative_to(store)) for p in gone}
    grid = [-(-n // c) for n, c in zip(radiance.shape, radiance.chunks, strict=True)]
    want = sorted(i for i in np.ndindex(*grid) if completeness.object_key(radiance, i) in keys)
    assert len(want) >= 2
    assert [i for i, _ in listed] == want and all(m for _, m in listed), scanned.err
    assert "lost after btf wrote them" in scanned.err
    named = ["for chunk c/" + "/".join(map(str, _grid_index(store, p))) + " " for p in gone]
    compressed = btf("compress", store, tmp_path / "c.zarr", "--rank", "4")
    assert compressed.code == 1 and f"{store}: array 'radiance' has no object for chunk " \
        in compressed.err, compressed.err
    cropped = btf("crop", store, tmp_path / "r.zarr", "--region", "0:32,0:32")
    assert cropped.code == 1 and any(n in cropped.err for n in named) \
        and "Traceback" not in cropped.err, cropped.err
    assert not (tmp_path / "c.zarr").exists() and not (tmp_path / "r.zarr").exists()


def _losing(monkeypatch, lost) -> None:
    """Chunk writes whose key ``lost(key)`` picks are acknowledged and never stored.

    Both ways chunks are written: zarr's ``LocalStore.set`` and btf's own whole-chunk writes
    (:mod:`pipeline.chunk_io`).
    """
    from pipeline import chunk_io

    set_, put = LocalStore.set, chunk_io._put

    async def store_set(self, key, value):
        if not lost(key):
            await set_(self, key, value)

    def direct(store, key, data):
        if not lost(key):
            put(store, key, data)

    monkeypatch.setattr(LocalStore, "set", store_set)
    monkeypatch.setattr(chunk_io, "_put", direct)


def test_a_write_lost_on_its_way_fails_the_stage_before_its_commit(tmp_path, btf, monkeypatch):
    reference = generate_store(tmp_path / "ref.zarr", *GEN)
    dropped = []

    def lose_one(key):
        if storage.chunk_key(key) and key.startswith("radiance/") and not dropped:
            dropped.append(key)  # acknowledged, never stored
            return True
        return False

    _losing(monkeypatch, lose_one)
    out = tmp_path / "g.zarr"
    run = btf("generate", out, *GEN)
    assert run.code == 1 and dropped, run.err
    assert f"{out}: 1 chunk object(s) are missing once the stage finished" in run.err
    assert dropped[0] in run.err and "run the same command again" in run.err
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["ref.zarr"]
    monkeypatch.undo()
    assert btf("generate", out, *GEN).code == 0
    a, b = (zarr.open_group(p, mode="r") for p in (reference, out))
    assert np.array_equal(a["radiance"][...], b["radiance"][...], equal_nan=True)


def test_every_chunk_is_written_even_one_equal_to_the_fill_value(tmp_path):
    array = zarr.create_array(storage.store(str(tmp_path / "a.zarr")), shape=(4, 8),
                              chunks=(4, 4), dtype="float32", fill_value=np.nan)
    array[:, :4] = np.nan
    array[:, 4:] = 0.0
    assert sorted(p.name for p in (tmp_path / "a.zarr" / "c" / "0").iterdir()) == ["0", "1"]


def test_stores_not_sealed_read_a_missing_chunk_as_fill_values(tmp_path, btf):
    store = generate_store(tmp_path / "g.zarr", *GEN)
    root = store / "zarr.json"  # as a store written before sealing
    meta = json.loads(root.read_text())
    del meta["attributes"][storage.SEALED]
    root.write_text(json.dumps(meta))
    gone = _chunk_files(store)[0]
    gone.unlink()
    radiance = zarr.open_array(storage.store(str(store)), path="radiance", mode="r")
    values = radiance[...]
    assert np.isnan(values).sum() == np.prod(radiance.chunks)
    scanned = btf("inspect", store, "--scan", "--json")
    assert scanned.code == 0, scanned.err
    writable = zarr.open_array(storage.store(str(store)), path="radiance", mode="r+")
    assert np.isnan(writable[...]).sum() == np.prod(radiance.chunks)


def test_a_write_lost_in_a_pyramid_leaves_the_store_as_it_was(tmp_path, btf, monkeypatch):
    store = generate_store(tmp_path / "g.zarr", *GEN)
    before = sorted(p.relative_to(store) for p in store.rglob("*"))
    dropped = []

    def lose_one(key):
        if ".partial-" in key and "/c/" in key and "zarr.json" not in key and not dropped:
            dropped.append(key)
            return True
        return False

    _losing(monkeypatch, lose_one)
    lost = btf("pyramid", store, "--levels", "2", "--quiet")
    assert lost.code == 1 and dropped, lost.err
    assert f"{store}: group 'pyramid': 1 chunk object(s) are missing" in lost.err, lost.err
    assert sorted(p.relative_to(store) for p in store.rglob("*")) == before
    monkeypatch.undo()
    assert btf("pyramid", store, "--levels", "2", "--quiet").code == 0
    assert btf("inspect", store, "--scan").code == 0
