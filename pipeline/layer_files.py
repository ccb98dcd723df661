"""Folders of layer images: their file names and ``manifest.csv``.

A layer folder holds one image per (view, light) layer. The directions of each image are in
``manifest.csv`` (``file,theta_light,phi_light,theta_view,phi_view``, exact angles) and in its
UTIA-style name ``tl{theta}_pl{phi}_tv{theta}_pv{phi}.{exr,png}`` (angles to 4 decimals).
``btf export`` and ``btf reconstruct --format exr`` write such folders, ``btf ingest`` reads
them back.
"""

from __future__ import annotations

import csv
import re
from collections.abc import Iterable
from pathlib import Path

MANIFEST = "manifest.csv"
MANIFEST_COLUMNS = ("file", "theta_light", "phi_light", "theta_view", "phi_view")
_NUMBER = r"(-?\d+(?:\.\d+)?)"
UTIA_NAME = re.compile(rf"tl{_NUMBER}_pl{_NUMBER}_tv{_NUMBER}_pv{_NUMBER}\.(exr|png)",
                       re.IGNORECASE)


def layer_name(theta_light, phi_light, theta_view, phi_view, suffix: str) -> str:
    """UTIA-style file name of a layer (angles to 4 decimals, trailing zeros dropped)."""
    def fmt(a: float) -> str:
        return f"{a:.4f}".rstrip("0").rstrip(".")

    return (f"tl{fmt(theta_light)}_pl{fmt(phi_light)}_tv{fmt(theta_view)}_"
            f"pv{fmt(phi_view)}.{suffix}")


def write_manifest(folder: Path, rows: Iterable[tuple]) -> None:
    """Write ``manifest.csv`` into ``folder``, the angles exactly (``repr`` of the float).

    ``rows`` are ``(file, theta_light, phi_light, theta_view, phi_view)``, one per layer.
    """
    with (Path(folder) / MANIFEST).open("w", newline="") as f:
        out = csv.writer(f)
        out.writerow(MANIFEST_COLUMNS)
        out.writerows([r[0], *(repr(float(a)) for a in r[1:])] for r in rows)
