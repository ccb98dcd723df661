"""The stages a run config or the command line can call, by name: one module per subcommand.

Each module holds its parameters (a frozen dataclass, :mod:`pipeline.params`), one function
that opens the inputs, builds its graph (:mod:`pipeline.graphs`) with kernels of :mod:`tasks`,
computes it on the session and writes the output store (:mod:`pipeline.stores`), and its
declaration ``STAGE`` (:class:`pipeline.stage.Stage`: help, cost estimate, what a scene may
restrict). No stage imports another: what two share lives below them.

This package finds the declarations itself: a new module with a ``STAGE`` is a new stage, with
no list to edit. :data:`ORDER` only says where the known ones appear in ``btf --help`` (the
order of a run); others follow, by name. :data:`STAGES` imports every stage's module on first
use; :func:`stage` imports only the one a command names, so that ``btf inspect`` does not pay
for the imports of quilting or enlargement.
"""

from __future__ import annotations

import pkgutil

from pipeline.declarations import collect, declared
from pipeline.stage import Stage

ORDER = ("generate", "ingest", "export", "preview", "crop", "compress", "reconstruct", "enlarge",
         "reference", "quilt", "roller", "render", "fit", "pyramid", "report", "scene",
         "view", "inspect")


def _declaration(module: str) -> Stage | None:
    return declared(__name__, module, "STAGE", Stage)


def _declarations() -> dict[str, Stage]:
    return collect(__name__, __path__, "STAGE", Stage, ORDER)


def stage(name: str) -> Stage | None:
    """The stage called ``name``, importing only its module when it is named after it.

    None when no stage has that name.
    """
    if name.isidentifier() and any(m.name == name for m in pkgutil.iter_modules(__path__)):
        declared = _declaration(name)
        if declared is not None and declared.name == name:
            return declared
    return __getattr__("STAGES").get(name)


def __getattr__(name: str):
    if name == "STAGES":  # every stage, imported once, on first use
        if "STAGES" not in globals():
            globals()["STAGES"] = _declarations()
        return globals()["STAGES"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["STAGES", "Stage", "stage"]
