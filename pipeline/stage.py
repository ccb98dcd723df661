"""What a stage declares about itself: one :class:`Stage` in its own module.

Every module of :mod:`pipeline.stages` ends with ``STAGE = Stage(...)``: its parameters, the
function that runs it, its help, whether it makes a store, its cost estimate for ``btf run
--plan``, why it computes its whole output when a scene needs only part of it, and how its
output's directions follow from its input's. :mod:`pipeline.stages` collects the declarations
(as :mod:`pipeline.stores` collects store kinds); the run planner (:mod:`pipeline.config`)
and the cost engine (:mod:`pipeline.planning`) read them and import no stage.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from pipeline.params import option


@dataclasses.dataclass(frozen=True)
class Stage:
    """A stage of the pipeline: a subcommand of ``btf`` and a step of ``btf run``.

    Attributes
    ----------
    name
        The subcommand and the key of a config's stage.
    params
        The frozen dataclass of its parameters (:mod:`pipeline.params`).
    run
        ``run(params, session)``: opens the inputs, computes, writes the output.
    summary, description
        The subcommand's one-line help and its ``--help`` text.
    makes_store
        Its output is a store whose provenance proves it up to date (``btf run`` skips it).
    estimate
        ``estimate(params, shapes) -> (StageEstimate, Shape) | None``: bytes read and written,
        tasks, memory and time for ``btf run --plan`` (:mod:`pipeline.planning`), from the
        shapes of its inputs; None (or no function) when its cost depends on the data.
    whole
        Why it computes its whole output even when a config's scene reads only part of it
        (``btf run --check``); None for stages that make no store a scene could read.
    for_scene
        It restricts its work to what a scene reads, through its ``for_scene`` parameter
        (:func:`for_scene_option`).
    directions
        ``directions(params, source) -> Directions | None``: its output's light and view
        directions, from those of its input store (``source``, None when it has none or
        they are not known); no function when its output has no directions to follow.
    """

    name: str
    params: type
    run: Callable[[Any, Any], Any]
    summary: str
    description: str
    makes_store: bool = False
    estimate: Callable[[Any, dict], Any] | None = None
    whole: str | None = None
    for_scene: bool = False
    directions: Callable[[Any, Any], Any] | None = None


def for_scene_option():
    """The ``--for-scene`` parameter of a stage declared with ``for_scene=True``."""
    return option(None, metavar="SCENE.yaml", path="in",
                  help="write only what this scene spec (or a run config's scene: section) "
                       "reads of OUT: its layers, and its texels unless OUT is a tile set; OUT "
                       "keeps its full shape, the rest unwritten (a tile set of a compressed "
                       "store is written whole: its eigentextures serve every layer)")


def same_directions(params, source):
    """The directions of a stage that keeps its input's (``Stage.directions``)."""
    return source


def selected_directions(params, source):
    """The directions of a stage that keeps its input's ``--view`` and ``--light`` choice."""
    if source is None:
        return None
    return source.select(params.view or range(source.views),
                         params.light or range(source.lights))
