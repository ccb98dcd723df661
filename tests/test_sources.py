"""The input formats are a registry of modules (issue 54): one module, one entry, nothing else.

Every module of ``pipeline/sources/`` declares one format; the registry finds them itself; no
module outside the package names one of them; and a new format, dropped into the package as a
module of its own, is read by ``btf ingest`` and described by ``btf inspect`` with no other
file touched.
"""

from __future__ import annotations

import ast
import importlib
import pkgutil
import re
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import zarr

import pipeline.sources as sources
from pipeline.sources import FORMATS, SourceFormat, source_format

ROOT = Path(__file__).resolve().parents[1]
MODULES = sorted(m.name for m in pkgutil.iter_modules(sources.__path__))


def test_every_module_of_the_package_declares_exactly_one_format():
    assert {"folder", "zip", "big", "dfmf"} <= set(MODULES)
    for name in MODULES:
        module = importlib.import_module(f"pipeline.sources.{name}")
        declared = [v for v in vars(module).values() if isinstance(v, SourceFormat)]
        assert declared == [module.FORMAT], name
        assert module.FORMAT.name == name  # the module is named after its format
        assert FORMATS[name] is module.FORMAT
    # ORDER places the known ones; any other follows by name
    assert list(FORMATS) == [n for n in sources.ORDER if n in FORMATS] + sorted(
        set(FORMATS) - set(sources.ORDER))
    assert len({f.name for f in FORMATS.values()}) == len(MODULES)  # names are unique
    assert len({f.noun for f in FORMATS.values()}) == len(MODULES)


def test_no_module_outside_the_package_names_a_format_s_module():
    """Code reaches a format only through the registry (tests may import their format)."""
    names = "|".join(MODULES)
    dotted = re.compile(rf"pipeline[./]sources[./]({names})\b")
    found = []
    for package in ("pipeline", "tasks", "benchmarks"):
        for path in (ROOT / package).rglob("*.py"):
            if path.parent == ROOT / "pipeline" / "sources":
                continue
            text = path.read_text()
            found += [f"{path.relative_to(ROOT)}: {m.group(0)}" for m in dotted.finditer(text)]
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, ast.ImportFrom) and node.module == "pipeline.sources":
                    found += [f"{path.relative_to(ROOT)}: imports {a.name}" for a in node.names
                              if a.name in MODULES]
    assert found == []


def test_the_help_of_ingest_and_inspect_lists_the_registry_s_formats(btf):
    for command in ("ingest", "inspect"):
        text = " ".join(btf(command, "--help").out.split())
        for f in FORMATS.values():
            assert f"{f.name} {' '.join(f.description.split())}" in text, (command, f.name)


def test_of_two_formats_that_can_open_a_path_its_name_chooses(tmp_path):
    big = b"BIG\0\0\0\0\0" + b"\0" * 16
    for name, content, chosen in [("a.zip", big, "zip"), ("a.big", b"PK\x03\x04", "big"),
                                  ("a.btf", b"PK\x03\x04", "dfmf"), ("a", big, "big"),
                                  ("b", b"PK\x05\x06", "zip")]:
        (tmp_path / name).write_bytes(content)
        assert source_format(tmp_path / name) is FORMATS[chosen], name
    (tmp_path / "folder.btf").mkdir()  # a folder named as a DFMF file: read as one, as before
    assert source_format(tmp_path / "folder.btf") is FORMATS["dfmf"]


# A format of its own for the test: an .npz of layers and their directions. It is written into
# a folder added to the package's path, so that the registry finds it like any other module.
NPZ_FORMAT = r'''
"""A test's format: an .npz with ``radiance`` (view, light, y, x, channel) and directions."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.images import ImageInfo
from pipeline.layer_sources import Entry, LayerSource, layer_grid
from pipeline.source_report import layers_lines, layers_report
from pipeline.sources import SourceFormat


@dataclass(frozen=True)
class NpzReader:
    path: str

    def where(self, key):
        return f"{self.path}: layer {key}"

    def __call__(self, key):
        with np.load(self.path) as f:
            return f["radiance"][key].astype(np.float32)


def _open(path, options):
    with np.load(path) as f:
        shape = f["radiance"].shape
        tv, pv, tl, pl = (f[k].tolist() for k in ("tv", "pv", "tl", "pl"))
    entries = [Entry((v, li), (tl[li], pl[li], tv[v], pv[v]), str(path), f"{v}.{li}")
               for v in range(shape[0]) for li in range(shape[1])]
    directions, grid = layer_grid(entries, str(path), ordered=True)
    return LayerSource(directions, grid, ImageInfo(shape[2], shape[3], ("R", "G", "B")),
                       NpzReader(str(Path(path).resolve())), {"format": "npz layers"},
                       "npz values stored as they are")


def describe(path):
    return layers_report(_open(path, None), kind="npz", file_bytes=path.stat().st_size,
                         directions_from="its arrays")


def guess_can_open(path):  # an .npz is a zip: by its name, or by a zip's first bytes
    if path.suffix == ".npz":
        return True
    if not path.is_file():
        return False
    with path.open("rb") as f:
        return f.read(4) == b"PK\x03\x04"


FORMAT = SourceFormat("npz", "an .npz of layers and directions (a test's format)",
                      "an .npz of layers", suffixes=(".npz",), guess_can_open=guess_can_open,
                      describe=describe, lines=layers_lines, open=_open)
'''


@pytest.fixture
def npz_format(tmp_path, monkeypatch):
    """The package with one more module, ``npz``, found by the registry as it finds the rest."""
    folder = tmp_path / "more_sources"
    folder.mkdir()
    (folder / "npz.py").write_text(textwrap.dedent(NPZ_FORMAT))
    assert sources.FORMATS  # found once, before: put back after the test
    monkeypatch.setattr(sources, "__path__", [*sources.__path__, str(folder)])
    monkeypatch.delitem(vars(sources), "FORMATS")
    yield
    sys.modules.pop("pipeline.sources.npz", None)


def test_a_new_format_is_its_module_alone(tmp_path, btf, npz_format):
    rng = np.random.default_rng(0)
    radiance = rng.random((2, 3, 4, 5, 3)).astype(np.float32)
    path = tmp_path / "m.npz"
    np.savez(path, radiance=radiance, tv=[0.0, 30.0], pv=[0.0, 90.0], tl=[0.0, 15.0, 45.0],
             pl=[0.0, 60.0, 300.0])
    assert list(sources.FORMATS)[-1] == "npz"
    r = btf("ingest", path, tmp_path / "m.zarr", "--scheduler", "synchronous")
    assert r.code == 0, r.err
    assert "ingest: colour: npz values stored as they are" in r.err
    group = zarr.open_group(tmp_path / "m.zarr", mode="r")
    assert np.array_equal(group["radiance"][...], radiance)
    assert group.attrs["ingest"] == {"format": "npz layers"}
    assert group["theta_light"][...].tolist() == [0.0, 15.0, 45.0]
    r = btf("inspect", path)
    assert r.code == 0, r.err
    assert f"{path}: npz layers" in r.out and "6 images (npz)" in r.out
    assert "btf ingest makes a radiance store of 2 views x 3 lights x 4 x 5 texels" in r.out
    (tmp_path / "notes.txt").write_text("hello")
    r = btf("ingest", tmp_path / "notes.txt", tmp_path / "n.zarr")
    assert r.code == 1 and "a .btf file (Bonn DFMF) or an .npz of layers" in r.err, r.err
    # a zip's first bytes and no name: the zip archives' format and this one both claim it
    unnamed = tmp_path / "m"
    unnamed.write_bytes(path.read_bytes())
    r = btf("ingest", unnamed, tmp_path / "u.zarr")
    assert r.code == 1 and not (tmp_path / "u.zarr").exists()
    assert (f"{unnamed}: could be a zip archive (UBO2003/ATRIUM) or an .npz of layers (by its "
            "name or its first bytes); btf cannot tell which") in r.err, r.err
    assert len(r.err.strip().splitlines()) == 1
