"""Orchestration of the BTF pipeline: stores, dask graphs, files, schedulers and the CLI.

The numerical kernels live in :mod:`tasks`; this package maps them over chunks and owns every
store, file and scheduler.
"""

from importlib.metadata import PackageNotFoundError, version

from pipeline._imports import defer_optional_imports

try:
    __version__ = version("btf-pipeline")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0+unknown"

defer_optional_imports()  # before any module of the package imports dask.array
