"""Outputs appear complete or not at all, and never replace what btf did not write."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import zarr

from helpers import generate_store
from pipeline.atomic import atomic_output
from pipeline.errors import BTFError

SMALL = ("--material", "tiles", "--size", "16", "--sampling", "hemi:2", "--chunk", "8")


def test_a_completed_output_replaces_the_old_one_only_with_overwrite(tmp_path):
    target = tmp_path / "out.txt"
    with atomic_output(target, directory=False) as tmp:
        tmp.write_text("first")
    with pytest.raises(BTFError, match="already exists; pass --overwrite"):
        with atomic_output(target, directory=False) as tmp:
            tmp.write_text("second")
    assert target.read_text() == "first"
    with atomic_output(target, directory=False, overwrite=True) as tmp:
        tmp.write_text("second")
    assert target.read_text() == "second"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_an_error_inside_removes_the_partial_output_and_keeps_the_old(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("good")
    with pytest.raises(ZeroDivisionError):
        with atomic_output(target, directory=False, overwrite=True) as tmp:
            tmp.write_text("half")
            1 / 0  # noqa: B018
    assert target.read_text() == "good"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_a_failed_swap_puts_the_good_output_back(tmp_path, monkeypatch):
    from pathlib import Path

    target = tmp_path / "out.txt"
    target.write_text("good")
    real = Path.rename

    def rename(self, new):
        if self.name.startswith(".out.partial"):
            raise OSError("device full")
        return real(self, new)

    monkeypatch.setattr(Path, "rename", rename)
    with pytest.raises(OSError, match="device full"):
        with atomic_output(target, directory=False, overwrite=True) as tmp:
            tmp.write_text("new")
    assert target.read_text() == "good"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_folders_btf_did_not_write_are_never_replaced(tmp_path):
    mine = tmp_path / "photos"
    mine.mkdir()
    (mine / "holiday.jpg").write_bytes(b"precious")
    with pytest.raises(BTFError, match="refusing to replace a folder that btf did not write"):
        with atomic_output(mine, directory=True, overwrite=True) as tmp:
            tmp.mkdir()
    with pytest.raises(BTFError, match="is a folder; refusing to replace it with a file"):
        with atomic_output(mine, directory=False, overwrite=True) as tmp:
            tmp.write_text("x")
    assert (mine / "holiday.jpg").read_bytes() == b"precious"


def test_commands_refuse_to_clobber_their_own_input(tmp_path, btf):
    store = generate_store(tmp_path / "s.zarr", *SMALL)
    for args in (("preview", store, store), ("inspect", store, "--plot", store),
                 ("export", store, store, "--overwrite")):
        result = btf(*args, "--quiet")
        assert result.code == 2 and "is also an input of this stage" in result.err, args
    assert (store / "zarr.json").is_file()


def test_preview_replaces_an_existing_sheet_only_with_overwrite(tmp_path, btf):
    store = generate_store(tmp_path / "s.zarr", *SMALL)
    sheet = tmp_path / "sheet.png"
    assert btf("preview", store, sheet, "--quiet").code == 0
    again = btf("preview", store, sheet, "--quiet")
    assert again.code == 1 and "already exists" in again.err
    assert btf("preview", store, sheet, "--quiet", "--overwrite").code == 0


def test_a_plot_may_not_replace_a_store(tmp_path, btf):
    store = generate_store(tmp_path / "s.zarr", *SMALL)
    other = generate_store(tmp_path / "t.zarr", *SMALL)
    result = btf("inspect", store, "--plot", other)
    assert result.code == 1 and "is a folder; refusing to replace it with a file" in result.err
    assert (other / "zarr.json").is_file()


def test_a_resumable_partial_output_is_found_again_and_cleaned_up(tmp_path):
    import shutil

    from pipeline.resume import DONE, Progress

    out, kept = tmp_path / "o.zarr", tmp_path / "kept"
    record = {"stage": "generate", "parameters": {"size": 8}}

    class Killed(Exception):
        pass

    def killed_run(skeleton: bool) -> Path:
        """The partial output a run killed after its skeleton and one unit leaves behind."""
        with pytest.raises(Killed), atomic_output(out, directory=True, resume=record) as tmp:
            tmp.mkdir()
            (tmp / "data").write_text("block 0")
            if skeleton:
                Progress(tmp).mark_created()
            assert Progress(tmp).memo("unit", lambda: 42) == (42, False)
            shutil.copytree(tmp, kept)
            raise Killed  # an error removes the partial output: put it back as a kill leaves it
        shutil.copytree(kept, tmp)
        shutil.rmtree(kept)
        return tmp

    partial = killed_run(skeleton=True)
    with atomic_output(out, directory=True, resume=record) as tmp:
        assert tmp == partial and Progress(tmp).created
        assert Progress(tmp).memo("unit", lambda: 0) == (42, True)  # not computed again
        assert Progress(tmp).count() == 1
    assert (out / "data").is_file() and not (out / DONE).exists()  # markers go before the swap
    shutil.rmtree(out)
    partial = killed_run(skeleton=True)
    with atomic_output(out, directory=True, resume={"other": "parameters"}) as tmp:
        assert not partial.exists() and tmp != partial  # a stale partial output goes
        tmp.mkdir()
    shutil.rmtree(out)
    partial = killed_run(skeleton=False)
    with atomic_output(out, directory=True, resume=record) as tmp:
        assert tmp == partial and not tmp.exists()  # no complete skeleton: started over
        tmp.mkdir()


def test_a_second_run_of_the_same_resumable_output_is_refused_while_the_first_writes(tmp_path):
    out, record = tmp_path / "o.zarr", {"stage": "generate"}
    with atomic_output(out, directory=True, resume=record) as tmp:
        with pytest.raises(BTFError, match=r"another btf run is writing this output .*\.lock"):
            with atomic_output(out, directory=True, resume=record):
                pass
        assert tmp.parent == tmp_path  # the first run's partial output is untouched
        tmp.mkdir()
    assert out.is_dir() and not list(tmp_path.glob(".o.zarr.lock"))  # the lock goes too


@pytest.fixture
def small_disk(tmp_path):
    """A 3 MiB tmpfs at ``tmp_path/disk``, unmounted at the end; skipped where mounting is not
    allowed (it needs root, or CAP_SYS_ADMIN in a container)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if shutil.which("mount") is None or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(disk)],
            capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


WOOD = ("--material", "wood", "--sampling", "hemi:4", "--seed", "2")


def test_a_full_disk_is_one_message_and_a_resumable_run_continues_once_space_is_freed(
        tmp_path, btf, small_disk):
    # 6 MiB: room for some of the 11 MB store's units (a view's radiance, 2.4 MB, or the
    # truth arrays), whatever order they run in, and not for all of them
    subprocess.run(["mount", "-o", "remount,size=6m", str(small_disk)], check=True)
    old = generate_store(small_disk / "g.zarr", *WOOD, "--size", "32")
    before = _files(old)
    full = btf("generate", old, *WOOD, "--size", "256", "--overwrite")
    assert full.code == 1 and "Traceback" not in full.err
    assert f"no space left on the disk of {small_disk}" in full.err, full.err
    assert "free space and run the same command again to continue" in full.err
    assert _files(old) == before  # the previous output untouched
    (partial,) = small_disk.glob(".g.resume-*.zarr")  # the work done so far, kept
    subprocess.run(["mount", "-o", "remount,size=64m", str(small_disk)], check=True)
    again = btf("generate", old, *WOOD, "--size", "256", "--overwrite")
    assert again.code == 0 and "resuming an interrupted run" in again.err, again.err
    assert not partial.exists()
    reference = generate_store(tmp_path / "ref.zarr", *WOOD, "--size", "256")
    assert zarr.open_group(old, mode="r")["radiance"][...].tobytes() == \
        zarr.open_group(reference, mode="r")["radiance"][...].tobytes()


def test_a_full_disk_under_an_output_that_cannot_resume_leaves_nothing(tmp_path, btf,
                                                                        small_disk):
    store = generate_store(tmp_path / "g.zarr", *WOOD, "--size", "256")
    full = btf("export", store, small_disk / "layers", "--format", "exr")
    assert full.code == 1 and "Traceback" not in full.err
    assert f"no space left on the disk of {small_disk}" in full.err, full.err
    assert "nothing was written" in full.err
    assert list(small_disk.iterdir()) == []
