"""The project's layout holds: no import cycles, layers import downwards only, a light CLI,
and every kind of store created through the shared base (codec, coordinates, channels)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from helpers import generate_store

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "tasks", "benchmarks")


def _modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = path
    return out


def _import_graph() -> dict[str, set[str]]:
    """Module -> project modules it imports (anywhere in the file, also inside functions)."""
    modules = _modules()
    edges = {m: set() for m in modules}
    for module, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            for name in names:
                while name and name not in modules:
                    name = name.rpartition(".")[0]
                if name and name != module and not module.startswith(name + "."):
                    edges[module].add(name)
    return edges


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_the_import_graph_has_no_cycles_and_layers_import_downwards():
    edges = _import_graph()
    assert len(edges) > 40 and edges["pipeline.cli"]  # the walk found the project
    assert _cycles(edges) == []
    breaks = [f"{m} -> {n}" for m, targets in edges.items() for n in targets
              if (m.startswith("tasks") and not n.startswith("tasks"))
              or (m.startswith("pipeline") and n.startswith("benchmarks"))]
    assert breaks == []


def test_no_stage_imports_another_and_the_engines_import_no_stage():
    """What two stages share lives below them; the cost engine reads their declarations."""
    edges = _import_graph()
    stages = {m for m in edges if m.startswith("pipeline.stages.")}
    crossing = {m: sorted(edges[m] & stages) for m in stages if edges[m] & stages}
    assert not crossing, crossing
    for engine in ("pipeline.planning", "pipeline.stage"):
        assert not edges[engine] & stages, (engine, sorted(edges[engine] & stages))


def test_every_stage_declares_itself_in_its_own_module():
    from pipeline.stages import STAGES

    for name, stage in STAGES.items():
        module = sys.modules[stage.run.__module__]
        assert module.__name__ == f"pipeline.stages.{name}", (name, module.__name__)
        assert module.STAGE is stage
        assert stage.params.__module__ == module.__name__


def _outside_stores() -> dict[str, ast.AST]:
    """The parsed modules of ``pipeline`` outside ``pipeline.stores``."""
    return {m: ast.parse(p.read_text()) for m, p in _modules().items()
            if m.startswith("pipeline") and not m.startswith("pipeline.stores")}


def _store_access(tree: ast.AST) -> list[str]:
    """Group openings and ``btf_kind`` strings in a module (line numbers)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if name == "open_group":
                found.append(f"line {node.lineno}: open_group")
        if isinstance(node, ast.Constant) and node.value == "btf_kind":
            found.append(f"line {node.lineno}: 'btf_kind'")
    return found


def test_stores_are_opened_and_their_kinds_told_in_stores_only():
    # stages and graphs take handles (pipeline.stores.open_store): no group opened elsewhere,
    # no kind told by comparing the btf_kind attribute
    found = {m: _store_access(tree) for m, tree in _outside_stores().items()}
    assert not {m: f for m, f in found.items() if f}, found
    assert _store_access(ast.parse("zarr.open_group(x)\nif a.get('btf_kind') == 'btf': pass"))


def test_no_stage_runs_another_and_config_stores_import_no_stage_or_graph():
    edges = _import_graph()
    stages = {m for m in edges if m.startswith("pipeline.stages.")}
    for module, path in _modules().items():
        if module in stages:  # the registry by name is for btf run, not for stages
            names = {n.id for n in ast.walk(ast.parse(path.read_text()))
                     if isinstance(n, ast.Name)}
            assert "STAGES" not in names, module
    assert not edges["pipeline.config"] & stages, sorted(edges["pipeline.config"] & stages)
    stores = {m for m in edges if m.startswith("pipeline.stores")}
    graphs = {m for m in edges if m.startswith("pipeline.graphs")}
    assert not {m: edges[m] & graphs for m in stores if edges[m] & graphs}


def test_the_cycle_finder_finds_a_cycle():  # the check above could not pass by accident
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


# scipy's and skimage's submodules load on first use (``scipy.ndimage.gaussian_filter``): 0.3 s
# that every btf command, and every rerun after a fault, paid for two stages' kernels
HEAVY = ("dask", "distributed", "zarr", "xarray", "numba", "matplotlib", "scipy.ndimage",
         "scipy.sparse", "scipy.fft", "scipy.spatial", "scipy.special", "skimage.morphology")


@pytest.mark.parametrize("argv", [["--help"], ["generate", "--help"], ["bench", "--help"]])
def test_help_loads_no_heavy_package(argv):
    code = ("import contextlib, io, sys\nfrom pipeline.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
            f"    try:\n        main({argv!r})\n    except SystemExit:\n        pass\n"
            "assert 'usage' in out.getvalue()\n"
            f"print(' '.join(m for m in {HEAVY!r} if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=ROOT, check=True)
    assert done.stdout.strip() == ""


def _stores(tmp_path: Path, btf) -> dict[str, Path]:
    """One store of every kind the project writes, made by its own stage."""
    src = generate_store(tmp_path / "s.zarr", "--material", "fabric", "--size", "32",
                         "--sampling", "abtf:4,2", "--chunk", "16")
    out = {"abtf": src}
    steps = {
        "compressed": ("compress", src, tmp_path / "c.zarr", "--rank", "4"),
        "tileset": ("quilt", src, tmp_path / "t.zarr", "--block", "16", "--overlap", "4",
                    "--size", "24,24"),
        "compressed-tileset": ("quilt", tmp_path / "c.zarr", tmp_path / "ct.zarr", "--block",
                               "16", "--overlap", "4", "--size", "24,24"),
        "surface": ("render", tmp_path / "t.zarr", tmp_path / "f.zarr", "--light", "1",
                    "--size", "40,50"),
        "hls-fit": ("fit", src, tmp_path / "h.zarr"),
        "btf": ("generate", tmp_path / "b.zarr", "--material", "wood", "--size", "16",
                "--sampling", "hemi:3"),
        "scene": ("scene", tmp_path / "scene.yaml", tmp_path / "sc.zarr"),
    }
    (tmp_path / "scene.yaml").write_text(f"source: {tmp_path / 'c.zarr'}\n"
                                         "directions: [[10, 20, 0, 0]]\nregion: [0, 8, 0, 8]\n")
    for kind, args in steps.items():
        result = btf(*args, "--quiet")
        assert result.code == 0, (kind, result.err)
        out[kind] = args[2] if args[0] != "generate" else args[1]
    return out


def test_every_kind_of_store_has_the_codecs_checksums_coordinates_and_channels(tmp_path, btf):
    import xarray as xr

    from pipeline.stores import KINDS

    stores = _stores(tmp_path, btf)
    assert set(stores) == set(KINDS)  # a new kind of store must be added here
    for kind, path in stores.items():
        group = zarr.open_group(path, mode="r")
        assert group.attrs["btf_kind"] == kind
        KINDS[kind].check(group, path)
        for name in ("theta_view", "phi_view", "theta_light", "phi_light", "channel"):
            assert name in group.array_keys(), (kind, name)
        coords = {"theta_view", "phi_view", "theta_light", "phi_light", "channel", "corner"}
        for name in set(group.array_keys()) - coords:
            compressor, checksum = group[name].compressors
            assert compressor.to_dict()["configuration"]["cname"] == "lz4", (kind, name)
            assert checksum.to_dict() == {"name": "crc32c"}, (kind, name)
            assert group[name].metadata.dimension_names, (kind, name)
        for name in set(group.array_keys()) & coords:  # every chunk carries its checksum
            assert [c.to_dict() for c in group[name].compressors] == [{"name": "crc32c"}]
        ds = xr.open_zarr(path, consolidated=False)  # the store contract: xarray opens it
        assert np.all(np.isfinite(ds["theta_light"].values)), kind
