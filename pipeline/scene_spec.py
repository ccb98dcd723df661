"""Scene specs: what a renderer's scene needs of a store (issue 15), validated with line numbers.

A scene spec is a YAML mapping (examples in ``configs/scenes/``)::

    source: out/scenes/leather_svd.zarr   # any store the project writes (see below)
    directions:                           # [theta_light, phi_light, theta_view, phi_view]
      - [0, 0, 0, 0]                      #   in degrees, or the word: all (every measured
      - [40, 90, 30, 180]                 #   layer, no interpolation)
    interpolation: barycentric            # or nearest (for directions that were not measured)
    region: [0, 256, 0, 512]              # Y0, Y1, X0, X1 in level-0 texels, ends exclusive
    level: 1                              # level of detail: 0 full resolution, n = 1/2^n
    rank: 16                              # compressed sources: components to use
    format: zarr                          # zarr, exr or png

Sources: radiance stores (``btf``/``abtf``), compressed stores (``btf compress`` and ``btf
enlarge``), tile sets (``btf quilt``/``btf roller``: the surface they cover, ``size: [H, W]``
at ``origin: [Y, X]``, placed with ``seed``, default the set's), and surface stores (``btf
render``). ``region``, ``size`` and ``origin`` are in level-0 texels; at level n the output
holds the level-n texels whose blocks the region touches.

Keys are checked here without opening the source (unknown keys, types, ranges, directions
below the horizon); :mod:`pipeline.scenes` checks them against the source (a region
outside it, a level beyond its pyramid, a rank above the stored one) and names the key and
its line the same way.
"""

from __future__ import annotations

import dataclasses
import difflib
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from tasks.directions import METHODS
from tasks.sampling import canonical_direction

FORMATS = ("zarr", "exr", "png")
KEYS = ("source", "directions", "interpolation", "region", "size", "origin", "level", "rank",
        "format", "seed", "chunk")
DIRECTION_FIELDS = ("theta_light", "phi_light", "theta_view", "phi_view")


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """A validated scene spec (see the module docstring).

    ``directions`` is None for ``all``, else ``(n, 4)`` degrees with phi in [0, 360).
    ``lines`` maps keys to their line in ``path`` (for error messages).
    """

    path: str
    source: str
    directions: np.ndarray | None = None
    interpolation: str = "barycentric"
    region: tuple[int, int, int, int] | None = None
    size: tuple[int, int] | None = None
    origin: tuple[int, int] = (0, 0)
    level: int = 0
    rank: int | None = None
    format: str = "zarr"
    seed: int | None = None
    chunk: int = 256
    lines: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)
    line: int = 1
    prefix: str = ""

    def error(self, key: str, message: str) -> BTFError:
        """A :class:`BTFError` naming the spec file, the key's line and the key."""
        line = self.lines.get(key, self.lines.get(key.split("[")[0], self.line))
        return BTFError(f"{self.path}:{line}: {self.prefix}{key}: {message}")

    def record(self) -> dict[str, Any]:
        """The spec as plain JSON values (for provenance)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
               if f.name not in ("path", "lines", "line", "prefix")}
        out["directions"] = "all" if self.directions is None else self.directions.tolist()
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}


def load(path: str | Path) -> SceneSpec:
    """Read and validate a scene spec file (see the module docstring).

    A run config (a mapping with ``stages``) gives its ``scene:`` section.
    """
    from pipeline.yaml_lines import read

    path = str(path)
    data = read(path, "scene spec")
    if isinstance(data, dict) and "stages" in data:
        if not isinstance(data.get("scene"), dict):
            raise BTFError(f"{path}: a run config without a 'scene:' section")
        section = data["scene"]
        rest = type(section)((k, v) for k, v in section.items() if k != "out")
        rest.line, rest.lines = section.line, section.lines
        return from_mapping(rest, path, prefix="scene.")
    return from_mapping(data, path)


def _ints(value, n: int) -> bool:
    return (isinstance(value, list) and len(value) == n
            and all(isinstance(v, int) and not isinstance(v, bool) for v in value))


def from_mapping(data: Any, path: str, prefix: str = "") -> SceneSpec:
    """Validate a scene mapping (from :func:`load` or a run config's ``scene:`` section).

    ``prefix`` is put before key names in messages (``scene.`` in a run config).
    """
    lines = dict(getattr(data, "lines", {}))
    line = getattr(data, "line", 1)
    items = data.get("directions") if isinstance(data, dict) else None
    for i, item_line in enumerate(getattr(items, "lines", [])):
        lines[f"directions[{i}]"] = item_line

    def fail(key: str, message: str):
        raise BTFError(f"{path}:{lines.get(key, line)}: {prefix}{key}: {message}")

    if not isinstance(data, dict):
        raise BTFError(f"{path}:{line}: {prefix or 'scene'}: expected a mapping with at least "
                       "'source' and 'directions'")
    for key in data:
        if key not in KEYS:
            close = difflib.get_close_matches(str(key), KEYS, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            fail(str(key), f"unknown key{hint}; known keys: {', '.join(KEYS)}")
    for key in ("source", "directions"):
        if key not in data:
            fail(key, "is required")
    values: dict[str, Any] = {}
    if not isinstance(data["source"], str) or not data["source"]:
        fail("source", f"expected the path of a store, got {data['source']!r}")
    values["source"] = data["source"]
    values["directions"] = _directions(data["directions"], fail)
    for key, choices in (("interpolation", METHODS), ("format", FORMATS)):
        if key in data:
            if data[key] not in choices:
                fail(key, f"expected one of {', '.join(choices)}, got {data[key]!r}")
            values[key] = data[key]
    if "region" in data:
        r = data["region"]
        if not _ints(r, 4):
            fail("region", f"expected [Y0, Y1, X0, X1] (integers, ends exclusive), got {r!r}")
        if not (0 <= r[0] < r[1] and 0 <= r[2] < r[3]):
            fail("region", f"{r} is empty or negative (need 0 <= Y0 < Y1 and 0 <= X0 < X1)")
        values["region"] = tuple(r)
    if "size" in data:
        if not _ints(data["size"], 2) or min(data["size"]) < 1:
            fail("size", f"expected [H, W] (positive integers), got {data['size']!r}")
        values["size"] = tuple(data["size"])
    if "origin" in data:
        if not _ints(data["origin"], 2):
            fail("origin", f"expected [Y, X] (integers), got {data['origin']!r}")
        values["origin"] = tuple(data["origin"])
    for key, least in (("level", 0), ("rank", 1), ("seed", 0), ("chunk", 16)):
        if key in data and not (key == "rank" and data[key] is None):
            v = data[key]
            if not isinstance(v, int) or isinstance(v, bool) or v < least:
                fail(key, f"expected an integer of at least {least}, got {v!r}")
            values[key] = v
    return SceneSpec(path=path, lines=lines, line=line, prefix=prefix, **values)


def _directions(value, fail) -> np.ndarray | None:
    if value == "all":
        return None
    if not isinstance(value, list) or not value:
        fail("directions", "expected 'all' or a list of [theta_light, phi_light, theta_view, "
                           f"phi_view] in degrees, got {value!r}")
    out, seen = [], {}
    for i, item in enumerate(value):
        key = f"directions[{i}]"
        if (not isinstance(item, list) or len(item) != 4 or not all(
                isinstance(a, int | float) and not isinstance(a, bool) for a in item)):
            fail(key, f"expected [theta_light, phi_light, theta_view, phi_view] in degrees, "
                      f"got {item!r}")
        if not all(np.isfinite(item)):
            fail(key, f"angles must be finite, got {item!r}")
        for name, theta in (("theta_light", item[0]), ("theta_view", item[2])):
            if theta < 0 or theta > 90:
                where = "below the horizon" if theta > 90 else "negative"
                fail(key, f"{name} {theta} is {where}: theta is measured from the surface "
                          "normal and must be between 0 and 90 degrees")
        row = [float(item[0]), float(item[1]) % 360.0, float(item[2]), float(item[3]) % 360.0]
        same = tuple(round(a, 9) for a in (*canonical_direction(*row[:2]),
                                           *canonical_direction(*row[2:])))
        if same in seen:
            fail(key, f"repeats directions[{seen[same]}]")
        seen[same] = i
        out.append(row)
    return np.array(out, np.float64)
