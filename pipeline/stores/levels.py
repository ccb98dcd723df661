"""Levels of detail in a store: where they are and how they are described.

``btf pyramid`` writes level n of a store's variable (``radiance``, or ``V`` of a compressed
store or tile set) under ``pyramid/N/`` and lists the levels in the root group's
``multiscales`` attribute, the layout of OME-NGFF 0.4 (datasets with scale and translation
transforms); ``btf inspect`` and ``btf scene`` read them from there. Kept in the store layer,
so that the stages that read levels do not import the stage that writes them.
"""

from __future__ import annotations

from pipeline.errors import BTFError
from pipeline.stores.base import RADIANCE

PYRAMID = "pyramid"


def variable_of(group, path: str) -> str:
    """The variable that has levels: ``radiance``, or ``V`` for a compressed store or tile set."""
    kind = group.attrs.get("btf_kind")
    if kind in ("tileset", "compressed-tileset") and group.attrs.get("placement") == "lattice":
        raise BTFError(f"{path}: a roller tile set: its tiles lie on a sheared lattice, so "
                       "level n of its surface is not made of level-n tiles; btf scene computes "
                       "its levels on the fly")
    if kind == "compressed-tileset" and group["V"].ndim == 3:
        raise BTFError(f"{path}: a compressed tile set that keeps the sample's eigentextures "
                       "and its tiles' prescriptions: its tiles are computed where they are "
                       "read, and btf scene and btf view compute their levels on the fly")
    if kind in ("compressed", "compressed-tileset"):
        return "V"
    if kind in ("abtf", "btf", "tileset") and RADIANCE in group:
        return RADIANCE
    raise BTFError(f"{path}: a {kind or 'non-btf'} store; btf pyramid takes a radiance, a "
                   "compressed or a quilted tile-set store")


def levels_of(group) -> list[dict]:
    """The store's levels from its ``multiscales`` attribute: path, factor, shape."""
    scales = group.attrs.get("multiscales") or []
    if not scales:
        return []
    out = []
    for d in scales[0]["datasets"]:
        scale = next(t["scale"] for t in d["coordinateTransformations"] if t["type"] == "scale")
        factor = int(max(scale))
        try:
            shape = list(group[d["path"]].shape)
        except KeyError:  # metadata naming a level that is not there (a store edited by hand)
            shape = None
        out.append({"path": d["path"], "factor": factor,
                    "level": factor.bit_length() - 1, "shape": shape})
    return out


def multiscales(name: str, dims: tuple[str, ...], count: int, method: str) -> list[dict]:
    """The ``multiscales`` attribute of ``count`` levels of variable ``name`` beyond level 0."""
    datasets = [_dataset(name, dims, 1)] + [_dataset(f"{PYRAMID}/{n}/{name}", dims, 2**n)
                                            for n in range(1, count + 1)]
    return [{"version": "0.4", "name": name, "axes": _axes(dims), "datasets": datasets,
             "type": "mean",
             "metadata": {"method": method,
                          "edges": "blocks beyond the last whole 2^n x 2^n block are left out"}}]


def _axes(dims: tuple[str, ...]) -> list[dict]:
    kinds = {"y": "space", "x": "space", "channel": "channel", "component": "other"}
    return [{"name": d, "type": kinds.get(d, "other")} for d in dims]


def _dataset(path: str, dims: tuple[str, ...], factor: int) -> dict:
    scale = [float(factor) if d in ("y", "x") else 1.0 for d in dims]
    shift = [(factor - 1) / 2 if d in ("y", "x") else 0.0 for d in dims]
    transforms = [{"type": "scale", "scale": scale}]
    if factor > 1:  # a level-n texel's centre sits at the centre of its level-0 block
        transforms.append({"type": "translation", "translation": shift})
    return {"path": path, "coordinateTransformations": transforms}
