"""``dask.array`` without xarray at start-up.

``dask.array.core`` imports xarray (and pandas with it) when it is itself imported, only to
tell a DataArray in ``from_array``: 0.4 s of every btf process's start-up, where most stages
open no Dataset. :func:`defer_xarray` has that one import fail quietly (dask's optional import
gives ``None``) and puts in its place an object that stands for xarray once it is imported.
Any ``import xarray`` elsewhere, in this thread or another, is untouched: a plain import,
when it is made.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys
import threading

_CORE = "dask.array.core"


class _NoDataArray:
    """What ``xarray.DataArray`` is before xarray is imported: nothing is an instance."""


class _XarrayOnUse:
    """Stands for the xarray module in ``dask.array.core``.

    ``from_array`` asks whether its argument is a DataArray at every call; before xarray is
    imported (or where it is made unimportable, ``sys.modules["xarray"] = None``) nothing can
    be one, so that question imports nothing. Other names are xarray's, once it is imported.
    """

    def __getattr__(self, name: str):
        if name.startswith("__"):  # copy, pickle and hasattr probes: not xarray's
            raise AttributeError(name)
        module = sys.modules.get("xarray")
        if module is None and name == "DataArray":
            return _NoDataArray
        try:
            import xarray
        except ImportError as exc:
            raise AttributeError(name) from exc
        return getattr(xarray, name)


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Runs ``dask.array.core`` with xarray unimportable in its thread, for that import only.

    While the module runs, this finder refuses ``xarray`` to the thread running it and to no
    other: nothing is put in ``sys.modules``, and an xarray another thread imports meanwhile
    is the real one (and ``dask.array.core`` then keeps it, if it was there first).
    """

    def __init__(self) -> None:
        self.loader: importlib.abc.Loader | None = None
        self.running: int | None = None  # the thread running dask.array.core's import

    def find_spec(self, name, path, target=None):
        if name == "xarray" and self.running == threading.get_ident():
            raise ModuleNotFoundError(f"{name} is imported at first use (pipeline._imports)",
                                      name=name)
        if name != _CORE or "xarray" in sys.modules:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path, target)
        if spec is None or spec.loader is None:
            return None
        self.loader, spec.loader = spec.loader, self
        return spec

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module) -> None:
        self.running = threading.get_ident()
        try:
            self.loader.exec_module(module)
        finally:
            self.running = None
        if getattr(module, "xr", False) is None:
            module.xr = _XarrayOnUse()

    def get_source(self, name):  # tracebacks and inspect read the module through its loader
        return self.loader.get_source(name)

    def __getattr__(self, name: str):  # the rest of the file loader's (get_code, path, ...)
        if name == "loader":
            raise AttributeError(name)
        return getattr(self.loader, name)


def defer_xarray() -> None:
    """Have ``dask.array``, when next imported, leave xarray to be imported at first use."""
    if _CORE not in sys.modules and not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder())
