"""Directions from the names of measured BTF images: Bonn's archives and UTIA's folders.

Bonn's UBO2003 and ATRIUM zip archives name their members ``tl{ddd} pl{ddd} tv{ddd}
pv{ddd}.jpg`` (or ``.hdr``): fields separated by spaces, whole degrees, usually behind a folder
per view and an index prefix, as in ``UBO2003/MANYFILES/tv030_pv030/00008 tl000 pl000 tv030
pv030.jpg``. UTIA's BTF database names its images ``tl000_pl000_tv000_pv000.png`` (or
``.exr``): underscores, three digits each, often in a folder per view. The four numbers are
theta and phi of the light, then of the view, in degrees (``theta`` from the normal).
"""

from __future__ import annotations

import re

BONN_SUFFIXES = (".jpg", ".jpeg", ".hdr")
UTIA_SUFFIXES = (".png", ".exr")

# The name may carry any prefix (an index, a folder) before "tl", separated by a space,
# an underscore or a dash; the directions end the name.
_BONN_NAME = re.compile(r"(?:.*[ _-])?tl(\d{1,3}) pl(\d{1,3}) tv(\d{1,3}) pv(\d{1,3})"
                        r"\.(jpe?g|hdr)", re.IGNORECASE)
_UTIA_NAME = re.compile(r"tl(\d{3})_pl(\d{3})_tv(\d{3})_pv(\d{3})\.(png|exr)", re.IGNORECASE)

Angles = tuple[float, float, float, float]


def basename(member: str) -> str:
    """The last part of a zip member name or path (``/`` separated, as zip names are)."""
    return member.replace("\\", "/").rsplit("/", 1)[-1]


def bonn_angles(member: str) -> Angles | None:
    """``(theta_light, phi_light, theta_view, phi_view)`` of a UBO2003/ATRIUM member name.

    ``None`` when the name (its last ``/`` part) does not end in
    ``tl{ddd} pl{ddd} tv{ddd} pv{ddd}.jpg|.hdr``.
    """
    match = _BONN_NAME.fullmatch(basename(member))
    return None if match is None else tuple(float(g) for g in match.groups()[:4])


def utia_angles(name: str) -> Angles | None:
    """``(theta_light, phi_light, theta_view, phi_view)`` of a UTIA database image name.

    ``None`` unless the name is exactly ``tl{ddd}_pl{ddd}_tv{ddd}_pv{ddd}.png|.exr`` with three
    digits per field (zero-padded), which is how UTIA names them and how ``btf export`` never
    does (it writes ``tl0``, not ``tl000``).
    """
    match = _UTIA_NAME.fullmatch(basename(name))
    return None if match is None else tuple(float(g) for g in match.groups()[:4])
