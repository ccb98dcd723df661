"""``dask.array`` without xarray, ``scipy.sparse`` and ``scipy.fftpack`` at start-up.

``dask.array`` imports three optional modules when it is itself imported, and most btf
processes use none of them: 0.7-1.0 s of every start-up on a 2-core machine.

- ``dask.array.core`` imports xarray (and pandas with it) only to tell a DataArray in
  ``from_array``;
- ``dask.array.chunk_types`` imports ``scipy.sparse`` to register its matrices and arrays as
  chunk types;
- ``dask.array.fft`` imports ``scipy.fftpack`` to refuse its functions in ``fft_wrap``.

:func:`defer_optional_imports` has each of those imports fail quietly: that module's own import
statement, in the thread running it, and nothing else (dask's optional imports are written to
survive it). It then puts back what dask would have had: an object that stands for xarray once
it is imported, the sparse chunk types registered when ``scipy.sparse`` is first imported, and
the ``scipy`` that ``fft_wrap`` checks. Any other import of these modules (from another module,
in this thread or another) is untouched: a plain import, when it is made.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys
import threading

#: dask's modules, and the optional import each one makes at its own import.
_CHUNK_TYPES, _SPARSE = "dask.array.chunk_types", "scipy.sparse"
_DEFERRED = {"dask.array.core": "xarray", _CHUNK_TYPES: _SPARSE, "dask.array.fft": "scipy.fftpack"}
#: the modules between an import statement and a finder (dask's optional import, importlib's)
_MACHINERY = frozenset({"importlib", "importlib._bootstrap", "importlib._bootstrap_external",
                        "dask._compatibility", __name__})


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


class _Wrapped(importlib.abc.Loader):
    """A module's own loader, with :class:`_Finder`'s work before and after its code runs."""

    def __init__(self, finder: _Finder, loader: importlib.abc.Loader) -> None:
        self.finder, self.loader = finder, loader

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module) -> None:
        self.finder.run(module, self.loader)

    def get_source(self, name):  # tracebacks and inspect read the module through its loader
        return self.loader.get_source(name)

    def __getattr__(self, name: str):  # the rest of the file loader's (get_code, path, ...)
        if name == "loader":
            raise AttributeError(name)
        return getattr(self.loader, name)


def _importer() -> str | None:
    """The module whose code asked for the import being found (import machinery skipped)."""
    frame = sys._getframe(2)
    while frame is not None:
        name = frame.f_globals.get("__name__")
        if name not in _MACHINERY:
            return name
        frame = frame.f_back
    return None


class _Finder(importlib.abc.MetaPathFinder):
    """Runs each of :data:`_DEFERRED`'s modules with its optional import refused to it.

    While such a module runs, this finder refuses its optional module to that module's own
    import statements in the thread running it, and to nothing else: not to another thread,
    nor to a module it imports in turn (pydata's ``sparse`` or cupy importing
    ``scipy.sparse``). Nothing is put in ``sys.modules``; a module another thread imports
    meanwhile is the real one.

    Once both ``dask.array.chunk_types`` (its own ``scipy.sparse`` refused) and a later
    ``scipy.sparse`` have run, whichever last, it registers scipy's sparse types with dask.
    """

    def __init__(self) -> None:
        self.refused = threading.local()  # per thread: (module, name) refused, innermost last
        self.lock = threading.Lock()
        self.finished: set[str] = set()  # chunk_types (deferred) and scipy.sparse, once run
        self.registered = False

    def find_spec(self, name, path, target=None):
        refused = getattr(self.refused, "pairs", ())
        if refused and (_importer(), name) in refused:
            raise ModuleNotFoundError(f"{name} is imported at first use (pipeline._imports)",
                                      name=name)
        deferred = _DEFERRED.get(name)
        if name == _SPARSE:  # dask's sparse chunk types may wait for it: see the class
            if self.registered:
                return None
        elif deferred is None or deferred in sys.modules:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path, target)
        if spec is None or spec.loader is None:
            return None
        spec.loader = _Wrapped(self, spec.loader)
        return spec

    def run(self, module, loader: importlib.abc.Loader) -> None:
        name = module.__name__
        deferred = _DEFERRED.get(name)
        pairs = self.refused.__dict__.setdefault("pairs", [])
        if deferred is not None:
            pairs.append((name, deferred))
        try:
            loader.exec_module(module)
        finally:
            if deferred is not None:
                pairs.pop()
        if name == "dask.array.core" and getattr(module, "xr", False) is None:
            module.xr = _XarrayOnUse()
        elif name == "dask.array.fft" and getattr(module, "scipy", False) is None:
            module.scipy = sys.modules.get("scipy")  # fft_wrap's check needs no fftpack
        elif name in (_CHUNK_TYPES, _SPARSE):
            self._finished(name, module)

    def _finished(self, name: str, module) -> None:
        """Register scipy's sparse types with dask once both modules have run."""
        if name == _CHUNK_TYPES and any(
                k.__module__.startswith(_SPARSE) for k in module._HANDLED_CHUNK_TYPES):
            self.registered = True  # its own import found scipy.sparse (another thread's)
            return
        with self.lock:
            self.finished.add(name)
            if self.registered or self.finished != {_CHUNK_TYPES, _SPARSE}:
                return
            chunk_types, sparse = sys.modules[_CHUNK_TYPES], sys.modules[_SPARSE]
            for kind in (getattr(sparse, "spmatrix", None), getattr(sparse, "sparray", None)):
                if kind is not None and kind not in chunk_types._HANDLED_CHUNK_TYPES:
                    chunk_types.register_chunk_type(kind)
            self.registered = True


def defer_optional_imports() -> None:
    """Have ``dask.array``, when next imported, leave its optional modules to their first use."""
    if "dask.array.core" not in sys.modules and not any(isinstance(f, _Finder)
                                                         for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder())
