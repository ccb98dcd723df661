"""``btf scene SCENE.yaml OUT``: exactly the directions, region, level and rank a scene asks for.

The stage declares its parameters and help; :mod:`pipeline.scenes` computes the scene
(:func:`pipeline.scenes.write_scene`, which ``btf run`` also calls for a config's ``scene:``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from pipeline.params import option
from pipeline.scene_spec import load
from pipeline.scenes import write_scene
from pipeline.session import Session
from pipeline.stage import Stage


@dataclasses.dataclass(frozen=True)
class SceneParams:
    """Parameters of ``btf scene``."""

    scene: str = option(help="scene spec (YAML; see configs/scenes/)", positional=True,
                        path="in", metavar="SCENE.yaml")
    out: str = option(help="output: a .zarr store (format zarr) or a folder of images "
                           "(exr, png)", positional=True, path="out")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")


def scene_stage(params: SceneParams, session: Session) -> Path:
    """``btf scene``: load the spec and write what it asks for."""
    return write_scene(load(params.scene), params.out, session, overwrite=params.overwrite)


STAGE = Stage("scene", SceneParams, scene_stage,
              "compute only what a scene needs: directions, region, level, rank",
              "Write exactly what a scene spec (YAML, see configs/scenes/) asks of a store: "
              "its light/view directions (measured or not: nearest or barycentric "
              "interpolation over the measured ones), its texel region (a tile set: a surface "
              "of any size at an origin), a level of detail (the store's pyramid level, or "
              "block means of level 0 computed on the fly) and, for compressed sources, a "
              "rank. Only the chunks the scene touches are read; the counts are logged and "
              "recorded. Output: a .zarr store, or a folder of EXR or PNG images.")
