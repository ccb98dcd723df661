"""tasks/ is pure numpy: no dask, zarr, xarray, OpenEXR or file I/O (docs/README.md, the split)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

TASKS = Path(__file__).resolve().parents[1] / "tasks"
BANNED = {"dask", "distributed", "zarr", "xarray", "OpenEXR", "imagecodecs", "matplotlib",
          "pipeline", "os", "pathlib", "shutil", "io", "pickle"}


def _imports(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module.split(".")[0]


def test_tasks_sources_import_nothing_banned():
    sources = sorted(TASKS.glob("*.py"))
    assert len(sources) >= 5
    for source in sources:
        tree = ast.parse(source.read_text(), filename=str(source))
        banned = set(_imports(tree)) & BANNED
        assert not banned, f"{source.name} imports {banned}"
        opens = [n for n in ast.walk(tree) if isinstance(n, ast.Call)
                 and isinstance(n.func, ast.Name) and n.func.id == "open"]
        assert not opens, f"{source.name} opens files"


def test_importing_every_task_module_loads_no_banned_package():
    modules = [f"tasks.{p.stem}" for p in sorted(TASKS.glob("*.py")) if p.stem != "__init__"]
    code = (f"import importlib, sys\nfor m in {modules!r}: importlib.import_module(m)\n"
            "print(' '.join(sorted(n for n in sys.modules if n.split('.')[0] in "
            "{'dask', 'distributed', 'zarr', 'xarray', 'OpenEXR', 'imagecodecs'})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == ""
