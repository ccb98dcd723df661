"""The stages a run config or the command line can call, by name: one module per subcommand.

Each module holds its parameters (a frozen dataclass, :mod:`pipeline.params`), one function
that opens the inputs, builds its graph (:mod:`pipeline.graphs`) with kernels of :mod:`tasks`,
computes it on the session and writes the output store (:mod:`pipeline.stores`), and its
declaration ``STAGE`` (:class:`pipeline.stage.Stage`: help, cost estimate, what a scene may
restrict). No stage imports another: what two share lives below them.

This package finds the declarations itself: a new module with a ``STAGE`` is a new stage, with
no list to edit. :data:`ORDER` only says where the known ones appear in ``btf --help`` (the
order of a run); others follow, by name.
"""

from __future__ import annotations

import importlib
import pkgutil

from pipeline.stage import Stage

ORDER = ("generate", "ingest", "export", "preview", "crop", "compress", "reconstruct", "enlarge",
         "reference", "quilt", "roller", "render", "fit", "pyramid", "report", "scene",
         "view", "inspect")


def _declarations() -> dict[str, Stage]:
    found = {}
    for module in pkgutil.iter_modules(__path__):
        stage = getattr(importlib.import_module(f"{__name__}.{module.name}"), "STAGE", None)
        if isinstance(stage, Stage):
            found[stage.name] = stage
    rank = {name: k for k, name in enumerate(ORDER)}
    return dict(sorted(found.items(), key=lambda item: (rank.get(item[0], len(ORDER)),
                                                        item[0])))


STAGES: dict[str, Stage] = _declarations()

__all__ = ["STAGES", "Stage"]
