"""``btf run``: YAML configs that list stages, validated completely before anything runs.

A config is a mapping::

    description: what the run is for           # optional
    scheduler: threads                         # optional; --scheduler overrides it
    workers: 2                                 # optional; --workers overrides it
    stages:
      - generate: {out: out/demo/wood.zarr, material: wood, size: 256, sampling: "abtf:12,6"}
      - inspect: {store: out/demo/wood.zarr}
    scene:                                     # optional: what the run is for (see below)
      out: out/demo/scene.zarr
      source: out/demo/wood.zarr
      directions: [[30, 0, 0, 0]]

Each stage takes the same parameters as its subcommand (underscores for dashes). Before any
stage runs, every key is checked: unknown keys, wrong types and missing required keys, and
inputs that neither exist nor are made by an earlier stage, are reported with their place in the
file (``FILE:LINE: stages[2].generate.size: ...``). Only PyYAML's safe loader is used (a
subclass that also records line numbers and rejects duplicate keys). Relative paths are relative
to the current directory. A stage whose output store already holds exactly what the stage would
make (same parameters and version, from its provenance) is skipped; other outputs are replaced.

A ``scene:`` section (a scene spec, :mod:`pipeline.scene_spec`, plus its ``out``) runs last, and
the stage that makes its source computes only what the scene reads: ``reconstruct`` only the
scene's layers and texels, ``quilt`` and ``roller`` of a radiance store apply their tiles only
to the scene's layers (all through their ``for_scene`` parameter, set to the config). Other
stages compute their whole output; their declaration says why (``Stage.whole``), and ``btf run
--check`` prints it per stage.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import yaml

from pipeline import storage, yaml_lines
from pipeline.errors import BTFError
from pipeline.params import ParamError, from_mapping, names_path, paths
from pipeline.provenance import command_line, up_to_date
from pipeline.session import RuntimeOptions, Session, check_scheduler
from pipeline.stages import STAGES, Stage
from pipeline.yaml_lines import Mapping

TOP_KEYS = ("description", "scheduler", "workers", "stages", "scene")
@dataclasses.dataclass(frozen=True)
class PlannedStage:
    """A validated stage of a run: its parameters and where it is in the file."""

    stage: Stage
    params: Any
    where: str

    @property
    def name(self) -> str:
        """The stage's name (its subcommand)."""
        return self.stage.name


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """A validated run config."""

    path: str
    stages: tuple[PlannedStage, ...]
    scheduler: str | None = None
    workers: int | None = None
    scene: Any = None  # a pipeline.scene_spec.SceneSpec
    scene_out: str | None = None


def _apply_overrides(stages: list, overrides: list[str], path: str) -> None:
    for text in overrides:
        target, eq, raw = text.partition("=")
        name, dot, key = target.partition(".")
        if not eq or not dot or not key:
            raise BTFError(f"--set {text!r}: expected STAGE.KEY=VALUE, e.g. generate.size=64")
        if name not in STAGES:
            raise BTFError(f"--set {text!r}: unknown stage {name!r}")
        hits = [item[name] for item in stages if isinstance(item, dict)
                and isinstance(item.get(name), dict)]
        if not hits:
            raise BTFError(f"--set {text!r}: {path} has no {name!r} stage")
        for params in hits:
            params[key] = yaml.safe_load(raw)


def load(path: str | Path, overrides: tuple[str, ...] = ()) -> RunConfig:
    """Read and validate a run config (see the module docstring); nothing runs.

    Raises
    ------
    BTFError
        Naming the file, line and key of the first problem.
    """
    path = str(path)
    data = yaml_lines.read(path, "config")

    def fail(line: int, where: str, message: str):
        raise BTFError(f"{path}:{line}: {where}: {message}")

    if not isinstance(data, dict):
        fail(1, "config", "expected a mapping with a 'stages' list")
    for key in data:
        if key not in TOP_KEYS:
            fail(data.lines[key], str(key), f"unknown key; known keys: {', '.join(TOP_KEYS)}")
    stages = data.get("stages")
    if not isinstance(stages, list) or not stages:
        fail(data.lines.get("stages", data.line), "stages", "expected a non-empty list of stages")
    scheduler, workers = data.get("scheduler"), data.get("workers")
    if scheduler is not None:
        try:
            check_scheduler(str(scheduler))
        except ValueError as exc:
            fail(data.lines["scheduler"], "scheduler", str(exc))
    if workers is not None and (not isinstance(workers, int) or isinstance(workers, bool)
                                or workers < 1):
        fail(data.lines["workers"], "workers", f"expected a positive integer, got {workers!r}")
    _apply_overrides(stages, list(overrides), path)

    planned, made = [], set()
    for i, item in enumerate(stages):
        line = stages.lines[i]
        if not isinstance(item, dict) or len(item) != 1:
            fail(line, f"stages[{i}]", "each stage is a mapping with one key, the stage name")
        (name, raw), = item.items()
        where = f"stages[{i}].{name}"
        if name not in STAGES:
            fail(line, f"stages[{i}]", f"unknown stage {name!r}; stages: {', '.join(STAGES)}")
        if raw is None:
            raw = Mapping()
        if not isinstance(raw, dict):
            fail(line, where, "expected a mapping of parameters")
        lines = getattr(raw, "lines", {})
        try:
            params = from_mapping(STAGES[name].params, raw)
        except ParamError as exc:
            fail(lines.get(exc.name, line), f"{where}.{exc.name}", exc.message)
        except ValueError as exc:
            fail(line, where, str(exc))
        for field in dataclasses.fields(params):
            if field.metadata.get("path") != "in" or getattr(params, field.name) is None:
                continue
            value = getattr(params, field.name)
            if storage.parse(value) not in made and not storage.any_below(storage.parse(value)):
                fail(lines.get(field.name, line), f"{where}.{field.name}",
                     f"{value!r} does not exist and no earlier stage makes it")
        made.update(storage.parse(p) for p in paths(params, "out"))
        planned.append(PlannedStage(STAGES[name], params, f"{path}:{line}: {where}"))
    if "scene" not in data:
        return RunConfig(path, tuple(planned), scheduler, workers)
    spec, out = _scene_section(data, path, made, fail)
    return RunConfig(path, _restricted(tuple(planned), spec, path), scheduler, workers, spec, out)


def _scene_section(data, path: str, made: set, fail):
    from pipeline.scene_spec import from_mapping

    section = data["scene"]
    line = data.lines["scene"]
    if not isinstance(section, dict):
        fail(line, "scene", "expected a mapping: a scene spec and its out")
    out = section.get("out")
    if not isinstance(out, str) or not out:
        fail(getattr(section, "lines", {}).get("out", line), "scene.out",
             "expected the path of the scene's output (.zarr, or a folder for exr/png)")
    rest = Mapping((k, v) for k, v in section.items() if k != "out")
    rest.line, rest.lines = section.line, section.lines
    spec = from_mapping(rest, path, prefix="scene.")
    if (spec.format == "zarr") != out.lower().endswith(".zarr"):
        fail(section.lines["out"], "scene.out", f"{out!r} does not suit format {spec.format} "
                                                "(zarr: a .zarr path; exr, png: a folder)")
    if storage.parse(spec.source) not in made and not storage.any_below(
            storage.parse(spec.source)):
        fail(section.lines["source"], "scene.source",
             f"{spec.source!r} does not exist and no stage makes it")
    return spec, out


def producer(stages, source: str) -> int | None:
    """Index of the last stage that makes ``source`` (None: it exists already)."""
    found = None
    for k, step in enumerate(stages):
        if names_path(step.params, "out", source):
            found = k
    return found


def _restricted(stages: tuple, spec, path: str) -> tuple:
    """The stages, the scene source's producer set to compute only what the scene needs."""
    k = producer(stages, spec.source)
    if k is None or not stages[k].stage.for_scene or _read_later(stages, k, spec.source):
        return stages
    step = stages[k]
    try:
        params = dataclasses.replace(step.params, for_scene=path)
    except ParamError:  # its own light/view/region (or exr output): it computes those
        return stages
    return (*stages[:k], dataclasses.replace(step, params=params), *stages[k + 1:])


def _read_later(stages, k: int, source: str) -> bool:
    """Whether a stage after the ``k``-th reads ``source`` (then it must be whole)."""
    return any(names_path(s.params, "in", source) for s in stages[k + 1:])


def scene_lines(plan: RunConfig) -> list[str]:
    """What each stage computes for the scene, in stored chunks (``btf run --check``)."""
    from pipeline import planning

    if plan.scene is None:
        return []
    shapes: dict = {}
    planning.plan_stages(plan.stages, shapes)
    k = producer(plan.stages, plan.scene.source)
    lines = [f"scene -> {plan.scene_out}: reads {plan.scene.source}"]
    for i, step in enumerate(plan.stages):
        outputs = paths(step.params, "out")
        shape = shapes.get(outputs[0]) if outputs else None
        src = shapes.get(getattr(step.params, "store", None))
        if (shape is None and step.name == "reconstruct" and src is not None and src.radiance
                and not (step.params.light or step.params.view or step.params.region)):
            layout = step.params.layout()
            shape = dataclasses.replace(src, kind="btf", chunk=layout.chunk,
                                        dir_chunk=layout.dir_chunk, unit=layout.chunk,
                                        itemsize=layout.itemsize)
        total = planning.chunks_of(shape) if shape is not None else None
        whole = f"all {total} chunks" if total else "all of its output"
        if getattr(step.params, "for_scene", None):
            what = _restricted_count(step, plan, shapes) or "only what the scene reads"
            lines.append(f"  {step.name}: restricted to the scene: {what}")
        elif i == k and _read_later(plan.stages, k, plan.scene.source):
            lines.append(f"  {step.name}: {whole}: a later stage reads its output too")
        elif i == k and step.stage.for_scene:
            lines.append(f"  {step.name}: {whole}: it was given its own light, view or region, "
                         "or writes EXR files")
        elif not outputs:
            lines.append(f"  {step.name}: writes no store")
        else:
            reason = step.stage.whole or "it makes no store the scene reads"
            lines.append(f"  {step.name}: {whole}: {reason}")
    return lines


def _restricted_count(step, plan: RunConfig, shapes: dict) -> str | None:
    """Stored chunks (or blocks of layers) a restricted stage computes, out of all."""
    import math

    from pipeline.planning import planned_directions
    from pipeline.scene_needs import needs_of

    d = planned_directions(plan.stages, step.params.store)
    src = shapes.get(step.params.store)
    if d is None or src is None or not src.radiance:
        return None  # its input's shape or directions are not known before it runs
    if step.name == "reconstruct":
        from pipeline.graphs.blocks import task_side

        ny, nx = src.radiance[2:4]
        needs = needs_of(plan.scene, d, (ny, nx))
        layout = step.params.layout()
        chunk, dl = layout.chunk, layout.dir_chunk
        side = task_side(chunk)  # written in task blocks of whole chunks
        kept = total = 0
        for view in range(d.views):
            for l0 in range(0, d.lights, dl):
                for y0 in range(0, ny, side):
                    for x0 in range(0, nx, side):
                        ys, xs = slice(y0, min(y0 + side, ny)), slice(x0, min(x0 + side, nx))
                        n = (math.ceil((ys.stop - ys.start) / chunk)
                             * math.ceil((xs.stop - xs.start) / chunk))
                        total += n
                        kept += n * needs.keeps(view, range(l0, min(l0 + dl, d.lights)), ys, xs)
        return (f"{kept} of {total} chunks (layers and texels {needs.window} of {ny} x {nx}: "
                "the task blocks holding them)")
    if src.kind == "compressed":
        return "all of its output: the eigentextures of a compressed source serve every layer"
    needs = needs_of(plan.scene, d)
    dl = src.dir_chunk
    blocks = [(view, l0) for view in range(d.views) for l0 in range(0, d.lights, dl)]
    kept = sum(needs.keeps(view, range(l0, min(l0 + dl, d.lights))) for view, l0 in blocks)
    return (f"{kept} of {len(blocks)} blocks of layers per tile ({len(needs.layers)} of "
            f"{needs.of} layers)")


def reset_peak_rss() -> bool:
    """Reset this process's peak resident memory (Linux: ``/proc/self/clear_refs``)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_rss() -> int | None:
    """Peak resident memory of the process since the last reset, in bytes (Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def execute(plan: RunConfig, session: Session) -> None:
    """Run the stages of a validated plan in order, skipping up-to-date stores."""
    start = time.perf_counter()
    skipped = 0
    for k, step in enumerate(plan.stages, 1):
        stage = step.stage
        outputs = paths(step.params, "out")
        header = f"[{k}/{len(plan.stages)}] {step.name}" + (f" -> {outputs[0]}" if outputs
                                                          else "")
        entry = {"stage": step.name, "out": outputs[0] if outputs else None,
                 "command": command_line(step.name, step.params)}
        if stage.makes_store and up_to_date(outputs[0], step.name, step.params):
            session.log(f"{header}: up to date, skipped")
            session.history.append({**entry, "skipped": True})
            skipped += 1
            continue
        session.log(header)
        params = step.params
        if "overwrite" in {f.name for f in dataclasses.fields(params)}:
            params = dataclasses.replace(params, overwrite=True)  # the run owns its outputs
        began, peak = time.perf_counter(), reset_peak_rss()
        stage.run(params, session)
        session.history.append({**entry, "skipped": False,
                                "seconds": time.perf_counter() - began,
                                "peak_rss": peak_rss() if peak else None})
    if plan.scene is not None:
        from pipeline.scenes import write_scene

        session.log(f"[scene] -> {plan.scene_out}")
        write_scene(plan.scene, plan.scene_out, session, overwrite=True)
    session.log(f"done: {len(plan.stages)} stage(s), {skipped} skipped, in "
                f"{time.perf_counter() - start:.1f} s")


def runtime_for(plan: RunConfig, options: RuntimeOptions, given: set[str]) -> RuntimeOptions:
    """Runtime options: the command line's where given, else the config's, else defaults."""
    changes = {}
    if "scheduler" not in given and plan.scheduler is not None:
        changes["scheduler"] = plan.scheduler
    if "workers" not in given and plan.workers is not None:
        changes["workers"] = plan.workers
    return dataclasses.replace(options, **changes)
