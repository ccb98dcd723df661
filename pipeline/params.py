"""Stage parameters declared once, used by the command line, YAML configs and provenance.

A stage's parameters are a frozen dataclass whose fields are made with :func:`option`: the help
text, the command-line form, and whether the field is an input or output path live next to the
type and default. :func:`add_arguments` turns the dataclass into argparse options,
:func:`from_mapping` validates a YAML mapping against it (unknown keys, wrong types, missing
keys), and :func:`to_record` writes it into a store's provenance.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import types
import typing
from collections.abc import Mapping
from typing import Any

from tasks.errors import InvalidParameter

MISSING = dataclasses.MISSING


# A parameter value that is not allowed; ``name`` is the offending field. The same class as
# the kernels' parameter errors, so a planner's refusal keeps the name of its parameter.
ParamError = InvalidParameter


def parse_region(text: str) -> tuple[slice, slice]:
    """``"Y0:Y1,X0:X1"`` as two slices (ends exclusive)."""
    try:
        ys, xs = (tuple(int(v) for v in part.split(":")) for part in text.split(","))
        (y0, y1), (x0, x1) = ys, xs
    except ValueError:
        raise ValueError(f"expected Y0:Y1,X0:X1 (texel ranges, ends exclusive), got "
                         f"{text!r}") from None
    if not (0 <= y0 < y1 and 0 <= x0 < x1):
        raise ValueError(f"region {text!r} is empty or negative")
    return slice(y0, y1), slice(x0, x1)


def check_region(text: str | None, name: str = "region") -> None:
    """Raise :class:`ParamError` for a region :func:`parse_region` refuses (None passes)."""
    if text is not None:
        try:
            parse_region(text)
        except ValueError as exc:
            raise ParamError(name, str(exc)) from None


def check_seed(seed: int | None) -> None:
    """Refuse a seed outside what numpy's generators take (``None``: nothing to check)."""
    if seed is not None and not 0 <= seed < 2**63:
        raise ParamError("seed", f"must be between 0 and 2**63 - 1, got {seed}")


def option(
    default: Any = MISSING,
    *,
    help: str,
    positional: bool = False,
    choices: tuple[str, ...] | None = None,
    metavar: str | None = None,
    path: str | None = None,
    record: bool = True,
    numbers_as_text: bool = False,
    key: str | None = None,
    repeatable: bool = False,
    group: str | None = None,
) -> Any:
    """A dataclass field of stage parameters.

    Parameters
    ----------
    default
        Default value; without one the parameter is required.
    help
        One-line explanation, shown by ``--help``.
    positional
        A positional command-line argument rather than an ``--option``.
    choices
        Allowed values.
    metavar
        Placeholder shown in usage lines.
    path
        ``"in"`` or ``"out"`` for paths a stage reads or writes (a run config checks that every
        input exists or is made by an earlier stage).
    record
        Whether the value is part of the provenance written into outputs (options that do not
        change results, such as ``overwrite``, are not).
    numbers_as_text
        A text option whose values may be written as YAML numbers (``passes: 1``,
        ``shrink: 0.5``).
    key
        The option's name on the command line and in configs, where the field's name cannot
        be it (``lambda``, a Python keyword); errors about it must name the key.
    repeatable
        A list option that may be given more than once on the command line; the lists join
        in order (``--light 2 --light 3,4`` is ``--light 2,3,4``).
    group
        A heading under which ``--help`` lists the option, after the stage's own options
        (options a mixin such as :class:`pipeline.stores.radiance.LayoutOptions` adds).
    """
    meta = {"help": help, "positional": positional, "choices": choices, "metavar": metavar,
            "path": path, "record": record, "numbers_as_text": numbers_as_text, "key": key,
            "repeatable": repeatable, "group": group}
    return dataclasses.field(default=default, metadata=meta)


def key_of(f: dataclasses.Field) -> str:
    """The name a parameter field has on the command line (dashed) and in configs."""
    return f.metadata.get("key") or f.name


def _base_type(tp: Any) -> tuple[Any, bool]:
    """The type without ``None`` and whether ``None`` is allowed."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0], len(args) < len(typing.get_args(tp))
    return tp, False


def int_list(text: str) -> tuple[int, ...]:
    """Parse ``"0,5,10"`` into ``(0, 5, 10)``."""
    try:
        return tuple(int(t) for t in str(text).split(",") if t.strip() != "")
    except ValueError:
        raise ValueError(f"expected comma-separated integers, got {text!r}") from None


def _describe(tp: Any) -> str:
    if typing.get_origin(tp) is tuple:
        return "a list of integers"
    return {int: "an integer", float: "a number", str: "a string", bool: "true or false"}[tp]


def coerce(value: Any, tp: Any, name: str, choices=None) -> Any:
    """Check a YAML value against a field type; strict (no string-to-number guessing)."""
    base, optional = _base_type(tp)
    if value is None:
        if optional:
            return None
        raise ParamError(name, f"expected {_describe(base)}, got nothing (null)")
    ok = False
    if base is bool:
        ok = isinstance(value, bool)
    elif base is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif base is float:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif base is str:
        ok = isinstance(value, str)
    elif typing.get_origin(base) is tuple:
        if isinstance(value, int) and not isinstance(value, bool):
            value = [value]
        if isinstance(value, str):
            try:
                value = list(int_list(value))
            except ValueError:
                value = None
        ok = isinstance(value, list) and all(
            isinstance(v, int) and not isinstance(v, bool) for v in value
        )
        value = tuple(value) if ok else value
    if not ok:
        raise ParamError(name, f"expected {_describe(base)}, got {value!r}")
    if choices and value not in choices:
        raise ParamError(name, f"{value!r} is not one of {', '.join(map(str, choices))}")
    return value


def check_paths(params: Any) -> Any:
    """Refuse bad paths, and an output that is also an input; returns ``params``.

    A bad path is a URL that names no place: an unsupported scheme, an ``s3`` URL without a
    key (:func:`pipeline.storage.parse`).
    """
    from pipeline import storage
    from pipeline.errors import BTFError

    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if f.metadata.get("path") and value is not None:
            try:
                storage.parse(value)
            except BTFError as exc:
                raise ParamError(f.name, str(exc)) from None
        if f.metadata.get("path") == "out" and value is not None:
            if names_path(params, "in", value):
                raise ParamError(f.name, f"{value!r} is also an input of this stage")
    return params


def from_mapping(cls: type, mapping: Mapping[str, Any]) -> Any:
    """Build parameters from a mapping (a YAML stage), naming any bad key.

    Raises
    ------
    ParamError
        For an unknown key (with the closest valid one), a wrong type or a missing key.
    """
    hints = typing.get_type_hints(cls)
    known = {key_of(f): f for f in dataclasses.fields(cls)}
    for key in mapping:
        if key not in known:
            close = difflib.get_close_matches(str(key), list(known), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ParamError(str(key), f"unknown key{hint}; known keys: {', '.join(known)}")
    values = {}
    for name, f in known.items():
        if name in mapping:
            value = mapping[name]
            if (f.metadata.get("numbers_as_text") and isinstance(value, int | float)
                    and not isinstance(value, bool)):
                value = str(value)
            values[f.name] = coerce(value, hints[f.name], name, f.metadata.get("choices"))
        elif f.default is MISSING:
            raise ParamError(name, "is required")
    return check_paths(cls(**values))


def to_record(params: Any) -> dict[str, Any]:
    """The parameters that determine a result, JSON-ready (tuples become lists)."""
    out = {}
    for f in dataclasses.fields(params):
        if f.metadata.get("record", True):
            value = getattr(params, f.name)
            out[key_of(f)] = list(value) if isinstance(value, tuple) else value
    return out


def paths(params: Any, direction: str) -> list[str]:
    """The input (``"in"``) or output (``"out"``) paths named by the parameters."""
    return [
        getattr(params, f.name)
        for f in dataclasses.fields(params)
        if f.metadata.get("path") == direction and getattr(params, f.name) is not None
    ]


def names_path(params: Any, direction: str, path: str) -> bool:
    """Whether the parameters name ``path`` among their inputs or outputs.

    Compared as locations: absolute paths or URLs.
    """
    from pipeline.storage import parse

    return parse(path) in {parse(p) for p in paths(params, direction)}


def add_arguments(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add one argparse argument per field of ``cls``."""
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    groups: dict[str, Any] = {}
    for f in (*[f for f in fields if not f.metadata.get("group")],
              *[f for f in fields if f.metadata.get("group")]):
        meta = f.metadata
        where = parser
        if meta.get("group"):
            if meta["group"] not in groups:
                groups[meta["group"]] = parser.add_argument_group(meta["group"])
            where = groups[meta["group"]]
        base, _ = _base_type(hints[f.name])
        help_text = meta["help"]
        if f.default not in (MISSING, None, False) and not meta["positional"]:
            shown = ",".join(map(str, f.default)) if isinstance(f.default, tuple) else f.default
            help_text += f" (default: {shown})"
        if meta.get("repeatable"):
            help_text += "; comma-separated, or the option repeated"
        kwargs: dict[str, Any] = {"help": help_text}
        if meta["choices"]:
            kwargs["choices"] = meta["choices"]
        if meta["metavar"]:
            kwargs["metavar"] = meta["metavar"]
        elif meta["positional"]:
            kwargs["metavar"] = f.name.upper()
        elif base in (int, float) and not meta["choices"]:
            kwargs["metavar"] = "N" if base is int else "X"
        elif base is str and not meta["choices"]:
            kwargs["metavar"] = "FILE" if meta["path"] else f.name.upper()
        if base is bool:
            kwargs["action"] = "store_true"
        elif typing.get_origin(base) is tuple:
            kwargs["type"] = int_list
            if meta.get("repeatable"):
                kwargs["action"] = _JoinLists
        else:
            kwargs["type"] = base
        if meta["positional"]:
            if f.default is not MISSING:  # an optional positional argument
                kwargs.update(nargs="?", default=f.default)
            where.add_argument(f.name, **kwargs)
        else:
            if f.default is MISSING:
                kwargs["required"] = True
            else:
                kwargs["default"] = f.default
            where.add_argument("--" + key_of(f).replace("_", "-"), dest=f.name, **kwargs)


class _JoinLists(argparse.Action):
    """Join the lists of an option given more than once (the first use replaces the default)."""

    def __call__(self, parser, namespace, values, option_string=None):
        seen = getattr(namespace, f"_{self.dest}_given", False)
        before = getattr(namespace, self.dest) if seen else ()
        setattr(namespace, self.dest, tuple(before) + tuple(values))
        setattr(namespace, f"_{self.dest}_given", True)


def from_namespace(cls: type, namespace: argparse.Namespace) -> Any:
    """Build parameters from parsed command-line arguments."""
    return check_paths(cls(**{f.name: getattr(namespace, f.name)
                              for f in dataclasses.fields(cls)}))
