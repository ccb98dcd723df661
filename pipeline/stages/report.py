"""``btf report``: one self-contained HTML page of what a run made and how well.

It shows, for whatever it is given:

- **the run**: each stage of the ``btf run`` that ends with this stage, with its time, its
  peak memory (this process's, reset before each stage: on a cluster the workers' memory is
  not in it) and the ``btf`` command that reproduces it;
- **compression** (``compressed``): rank, the size ratio of the BTF matrix to its factors, the
  error the store records (log domain) and eq. (11) of paper 000 against its source store
  (linear radiance), with a few layers of both side by side;
- **enlargement** (``enlarged``, with ``truth``): eq. (11) over the texels outside the sample
  for the enlargement, the oracle (each texel copies the sample ABRDF nearest to the truth's:
  the best a copy can do) and two baselines, the sample tiled periodically and the per-texel
  lookup, with the share of the gap from the oracle to the lookup each leaves and its
  realism (:mod:`tasks.realism`), and ground truth, enlargement and baselines side by side
  for a few lights;
- **tile set** (``tiles``): its border check, seam and structure per tile;
- **pictures**: PNG files or folders of them (a rendered surface, a scene's images).

Errors are evaluated in bands of texel rows, so memory follows the band, not the store; the
pictures show a window of at most ``--window`` texels per side.
"""

from __future__ import annotations

import dataclasses
import io
import time
from pathlib import Path

import numpy as np

from pipeline import __version__, storage
from pipeline.atomic import write_whole
from pipeline.errors import BTFError
from pipeline.params import ParamError, option
from pipeline.session import Session
from pipeline.stage import Stage
from pipeline.stores import CompressedStore, RadianceStore, TileSetStore, open_store
from tasks.evaluation import (
    abrdf_errors,
    abrdf_index,
    gap_share,
    lookup_baseline,
    nearest_abrdfs,
    tiling_baseline,
)
from tasks.realism import log_luminance, realism
from tasks.report_html import Picture, Section, Table, render
from tasks.svd import reconstruct_layers
from tasks.tonemap import exposure, tonemap
from tasks.transform import Transform

BAND = 64  # texel rows per band of the error evaluation


@dataclasses.dataclass(frozen=True)
class ReportParams:
    """Parameters of ``btf report``."""

    out: str = option(help="HTML file to write (a local path or an s3:// URL)",
                      positional=True, path="out")
    truth: str | None = option(None, path="in", metavar="STORE",
                               help="ground-truth radiance store the enlargement is judged by")
    compressed: str | None = option(None, path="in", metavar="STORE",
                                    help="a compressed store made by btf compress")
    enlarged: str | None = option(None, path="in", metavar="STORE",
                                  help="a compressed store made by btf enlarge")
    tiles: str | None = option(None, path="in", metavar="STORE",
                               help="a tile set made by btf quilt")
    pictures: str | None = option(None, metavar="PNG,..",
                                  help="PNG files, or folders of them, to show (comma-separated)")
    viewer: str | None = option(None, path="in", metavar="PAGE.html",
                                help="a relighting page (btf view) to link to")
    mitsuba: str | None = option(None, path="in", metavar="PNG",
                                 help="a picture made by btf mitsuba (the tile set on a "
                                      "sphere, say), shown beside the relighting page's link")
    lights: int = option(3, help="light directions shown side by side (spread over them)")
    window: int = option(256, help="largest side of the pictures' window, in texels")
    title: str = option("btf report", help="title of the page")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        if self.lights < 1:
            raise ParamError("lights", f"must be at least 1, got {self.lights}")
        if self.window < 16:
            raise ParamError("window", f"must be at least 16 texels, got {self.window}")


def _png(image: np.ndarray) -> bytes:
    from matplotlib.image import imsave

    buffer = io.BytesIO()
    imsave(buffer, np.clip(image, 0, 1), format="png")
    return buffer.getvalue()


def _factors(path: str):
    store = open_store(path, CompressedStore)
    group = store.group
    return (group, np.asarray(group["U"][...], np.float64), np.asarray(group["S"][...],
                                                                         np.float64),
            store.transform)


def _row_scale(group, transform: Transform) -> np.ndarray | None:
    """A cosine store's scale of every BTF-matrix row (view, light, channel), else None."""
    scale = transform.layer_scale(np.asarray(group["theta_light"][...], np.float64))
    if scale is None:
        return None
    nv, nc = group["theta_view"].shape[0], group["channel"].shape[0]
    return np.repeat(np.tile(scale, nv), nc)


def _spread(count: int, lights: int) -> list[int]:
    return sorted({int(i) for i in np.linspace(0, lights - 1, min(count, lights))})


def _rows(radiance, ys: slice) -> np.ndarray:
    """``(h, W, rows)`` linear radiance of a band, rows in BTF-matrix order."""
    block = np.asarray(radiance[:, :, ys], np.float64)  # (views, lights, h, W, channels)
    nv, nl, h, w, nc = block.shape
    return np.moveaxis(block, (0, 1), (2, 3)).reshape(h, w, nv * nl * nc)


def _values(transform: Transform, rows: np.ndarray, channels: int) -> np.ndarray:
    """The store's values of ``(h, W, rows)`` radiance rows (channel fastest)."""
    h, w, n = rows.shape
    return transform.encode(rows.reshape(h, w, n // channels, channels)).reshape(h, w, n)


def _fmt(x: float | None, digits: int = 4) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


def _sidecar(out: str) -> str:
    """Where the page's run history is kept: ``OUT`` with ``.json`` for its suffix."""
    location = storage.parse(out, what="output")
    name = storage.name(location)
    stem = name.rsplit(".", 1)[0] if "." in name else name
    sidecar = stem + ".json" if stem + ".json" != name else name + ".json"
    return storage.join(storage.parent(location), sidecar)


def _history(session: Session, out: str) -> list[dict]:
    """The run's stages; a skipped one keeps the time and memory of the run that made it.

    They are kept beside the page (``OUT.json``), by command: a rerun that skips up-to-date
    stages still reports what they cost.
    """
    import json

    previous = {}
    try:
        previous = {h["command"]: h for h in json.loads(storage.read(_sidecar(out)) or b"{}"
                                                        )["history"]}
    except (ValueError, KeyError, TypeError):
        pass
    history = []
    for h in session.history:
        before = previous.get(h["command"])
        if h["skipped"] and before is not None and "seconds" in before:
            h = {**before, "skipped": True, "measured_before": True}
        history.append(h)
    return history


def _stages(history: list[dict]) -> Section | None:
    if not history:
        return None
    rows, commands = [], []
    for h in history:
        peak = h.get("peak_rss")
        memory = "-" if peak is None else f"{peak / 2**20:.0f} MiB"
        if "seconds" not in h:
            rows.append((h["stage"], h["out"] or "-", "-", "-", "up to date, skipped"))
        else:
            note = "up to date: time of the run that made it" if h.get("measured_before") else ""
            rows.append((h["stage"], h["out"] or "-", f"{h['seconds']:.1f} s", memory, note))
        commands.append(h["command"])
    total = sum(h.get("seconds", 0.0) for h in history)
    return Section("The run", (f"{len(rows)} stages before this report, {total:.1f} s in all. "
                               "Peak memory is this process's, reset before each stage (on a "
                               "cluster the workers' memory is not in it).",),
                   (Table(("stage", "output", "time", "peak memory", "note"), tuple(rows)),),
                   commands=tuple(commands))


def _compression(path: str, params: ReportParams) -> Section:
    group, u, s, transform = _factors(path)
    v = group["V"]
    nv, nl, nc, k = u.shape
    ny, nx = v.shape[:2]
    matrix = nv * nl * nc * ny * nx
    factors = u.size + s.size + ny * nx * k
    error = dict(group.attrs.get("error", {}))
    source = dict(group.attrs.get("provenance", {})).get("parameters", {}).get("store")
    rows = [("rank", str(k)), ("BTF matrix", f"{nv * nl * nc} x {ny * nx}"),
            ("size ratio, matrix / factors", f"{matrix / factors:.1f}x"),
            ("relative error, log domain (recorded)",
             _fmt(error.get("log_relative_frobenius")))]
    pictures = []
    row_scale = _row_scale(group, transform)
    made_from = (open_store(source).group
                 if source and storage.any_below(storage.parse(source)) else None)
    if made_from is not None and "radiance" not in made_from:
        rows.append(("ABRDF RMSE against the source", "- (made from a compressed store: "
                                                      "compare with the radiance it came from)"))
    elif made_from is not None:
        radiance = made_from["radiance"]
        flat_u = u.reshape(-1, k)
        total, count = 0.0, 0
        for y0 in range(0, ny, BAND):
            ys = slice(y0, min(y0 + BAND, ny))
            coef = np.asarray(v[ys], np.float64) * s
            e = abrdf_errors(flat_u, coef, transform, _rows(radiance, ys),
                             np.ones(coef.shape[:2], bool), row_scale)
            total, count = total + e.sum(), count + e.size
        rows.append(("ABRDF RMSE against the source, linear (eq. 11)", _fmt(total / count)))
        w = min(params.window, ny, nx)
        vw = np.asarray(v[:w, :w], np.float64)
        for li in _spread(params.lights, nl):
            truth = np.asarray(radiance[0, li, :w, :w], np.float64)
            scale = exposure(truth)
            pictures += [Picture(f"source, light {li}", _png(tonemap(truth, scale=scale))),
                         Picture(f"rank {k}, light {li}",
                                 _png(tonemap(reconstruct_layers(
                                     u[0, li], s, vw, transform=transform,
                                     scale=None if row_scale is None
                                     else row_scale[li * nc]),
                                              scale=scale)))]
    return Section(f"Compression: {path}", (
        "Log range reduction and a randomized SVD: any layer is exp(U S V^T) - eps.",),
        (Table(("figure", "value"), tuple(rows)),), tuple(pictures))


def _truth(truth_path: str, path: str, texels: tuple[int, int], u_shape: tuple[int, ...]):
    """``--truth``'s radiance, refused unless it has the enlarged store's texels and layers."""
    (ny, nx), truth = texels, open_store(truth_path, RadianceStore).radiance
    if tuple(truth.shape[2:4]) != (ny, nx):
        raise BTFError(f"--truth {truth_path}: {truth.shape[2]} x {truth.shape[3]} texels, "
                       f"but {path} has {ny} x {nx}")
    layers = truth.shape[0] * truth.shape[1] * truth.shape[4]
    if layers != u_shape[0] * u_shape[1] * u_shape[2]:
        raise BTFError(f"--truth {truth_path}: {layers} textures (views x lights x "
                       f"channels), but {path} has {u_shape[0] * u_shape[1] * u_shape[2]}: "
                       "give the store the sample was measured from")
    return truth


def _errors_outside(truth, v, s, flat_u, flat_us, sample, sample_keys, keys_of, origin,
                    transform, scale=None) -> tuple[dict[str, float], int]:
    """Mean ABRDF RMSE (eq. 11) outside the sample, and the texels counted.

    For the enlargement, its oracle and the two baselines, band by band of texels.
    """
    ny, nx = v.shape[:2]
    sh, sw = sample.shape[:2]
    sums = {"oracle (nearest sample ABRDF)": 0.0, "enlargement": 0.0, "tiling": 0.0,
            "lookup": 0.0}
    count, index = 0, None
    for y0 in range(0, ny, BAND):
        ys = slice(y0, min(y0 + BAND, ny))
        rows = _rows(truth, ys)
        yy, xx = np.arange(ys.start, ys.stop)[:, None], np.arange(nx)[None, :]
        mask = ~((yy >= origin[0]) & (yy < origin[0] + sh) & (xx >= origin[1])
                 & (xx < origin[1] + sw))
        coef = np.asarray(v[ys], np.float64) * s
        tiled = tiling_baseline(sample, (ys.stop - ys.start, nx), origin, (ys.start, 0))
        looked = lookup_baseline(sample, sample_keys, keys_of(ys))
        if index is None:  # the sample's ABRDFs, searched for every band
            index = abrdf_index(flat_us, sample, transform, scale)
        best = sample.reshape(-1, sample.shape[-1])[nearest_abrdfs(flat_us, sample, transform, rows,
                                                                   index, scale)]
        for name, (basis, c) in {"oracle (nearest sample ABRDF)": (flat_us, best),
                                 "enlargement": (flat_u, coef), "tiling": (flat_us, tiled),
                                 "lookup": (flat_us, looked)}.items():
            sums[name] += abrdf_errors(basis, c, transform, rows, mask, scale).sum()
        count += int(mask.sum())
    return {n: sums[n] / max(count, 1) for n in sums}, count


def _enlargement(path: str, params: ReportParams) -> Section:
    group, u, s, transform = _factors(path)
    info = dict(group.attrs.get("enlargement", {}))
    parameters = dict(group.attrs.get("provenance", {})).get("parameters", {})
    paragraphs = [f"Synthesized from the compressed sample {parameters.get('sample')} under "
                  f"the photos {parameters.get('constraints')} (paper 000)."]
    if params.truth is None:
        return Section(f"Enlargement: {path}", (*paragraphs,
                       "No ground truth given (--truth): no error figures."))
    v = group["V"]
    ny, nx, k = v.shape
    truth = _truth(params.truth, path, (ny, nx), u.shape)
    sample_group, us, ss, _ = _factors(parameters["sample"])
    vs = np.asarray(sample_group["V"][...], np.float64)
    sample = vs * ss
    sh, sw = sample.shape[:2]
    origin = tuple(info.get("placement", {}).get("origin", (0, 0)))
    photo_group = open_store(parameters["constraints"], RadianceStore).group
    photos = photo_group["radiance"]
    # a cosine sample's values are radiance x cos(theta_light): the photos' are made alike
    photo_scale = _row_scale(photo_group, transform)
    keys_of = lambda ys: _values(  # noqa: E731
        transform, _rows(photos, ys) / (1.0 if photo_scale is None else photo_scale),
        u.shape[2])
    row_scale = _row_scale(group, transform)
    sample_keys = keys_of(slice(origin[0], origin[0] + sh))[:, origin[1] : origin[1] + sw]
    errors, count = _errors_outside(truth, v, s, u.reshape(-1, k),
                                    us.reshape(-1, us.shape[-1]), sample, sample_keys,
                                    keys_of, origin, transform, row_scale)
    oracle = errors["oracle (nearest sample ABRDF)"]
    pictures, looks = [], {}
    w = min(params.window, ny, nx)
    window = slice(0, w)
    coef_w = np.asarray(v[window, window], np.float64) * s
    tiled_w = tiling_baseline(sample, (w, w), origin)
    looked_w = lookup_baseline(sample, sample_keys, keys_of(window)[:, :w])
    for li in _spread(params.lights, u.shape[1]):
        true = np.asarray(truth[0, li, :w, :w], np.float64)
        scale = exposure(true)
        pictures.append(Picture(f"ground truth, light {li}", _png(tonemap(true, scale=scale))))
        for name, basis, c in (("enlargement", u, coef_w), ("tiling", us, tiled_w),
                               ("lookup", us, looked_w)):
            layer = reconstruct_layers(basis[0, li], np.ones(c.shape[-1]), c, transform=transform,
                                       scale=None if row_scale is None
                                       else row_scale[li * u.shape[2]])
            pictures.append(Picture(f"{name}, light {li}", _png(tonemap(layer, scale=scale))))
            looks.setdefault(name, []).append(realism(log_luminance(layer),
                                                      log_luminance(true)))
    table = Table(("method", "ABRDF RMSE outside the sample (eq. 11, linear)",
                   "share of the gap from the oracle to the lookup left", "realism"),
                  tuple((n, _fmt(e), f"{gap_share(e, errors['lookup'], oracle):.2f}",
                         _fmt(float(np.mean(looks[n])), 2) if n in looks else "")
                        for n, e in errors.items()))
    correlation = info.get("placement", {}).get("correlation", 0.0)
    paragraphs.append(f"The sample ({sh} x {sw}) sits at {origin[0]},{origin[1]} in the photos "
                      f"(correlation {correlation:.4f}); the errors count the {count} texels "
                      "outside it. The oracle is the best a copy of the sample's ABRDFs can do: "
                      "each texel takes the sample ABRDF nearest to the truth's. Realism: "
                      "texture statistics of the pictured window's log luminance against the "
                      "truth's, over those of two halves of the truth (1 = as alike as the "
                      "truth is to itself; tasks/realism.py), averaged over the lights shown.")
    return Section(f"Enlargement: {path}", tuple(paragraphs), (table,), tuple(pictures))


def _tiles(path: str) -> Section:
    group = open_store(path, TileSetStore).group
    check = dict(group.attrs.get("border_check", {}))
    tiles = check.get("tiles", [])
    rows = tuple((t["tile"], _fmt(t["seam"], 3), _fmt(t["structure"], 3), str(t["plans"]),
                  t["worst"]) for t in tiles)
    quilt = dict(group.attrs.get("quilt", {}))
    text = (f"{len(tiles)} tile(s) of {quilt.get('tile')} texels, block {quilt.get('block')}, "
            f"overlap {quilt.get('overlap')}, {quilt.get('corners')} corner type(s). Each "
            f"border's seam and structure against the tile's inside (1.00 = as good as the "
            f"inside; bound {check.get('bound')}).")
    return Section(f"Tile set: {path}", (text,),
                   (Table(("tile", "seam", "structure", "plans", "worst line"), rows),))


def _pictures(items: str) -> Section:
    pictures = []
    for item in filter(None, (i.strip() for i in items.split(","))):
        path = Path(item)
        files = sorted(path.glob("*.png")) if path.is_dir() else [path]
        if not files or not all(f.is_file() for f in files):
            raise BTFError(f"--pictures: {item}: no such PNG file or folder of PNGs")
        pictures += [Picture(str(f), f.read_bytes()) for f in files[:12]]
    return Section("Pictures", (), (), tuple(pictures))


def _viewer(page: str | None, out: str, render: str | None) -> Section:
    """The relighting page's link and a picture made by ``btf mitsuba`` beside it.

    The link is relative to the report where both are local files.
    """
    import os

    from pipeline.images import png_text

    paragraphs, links, pictures = [], (), ()
    if page is not None:
        href = page
        if not storage.is_url(page) and not storage.is_url(out):
            href = os.path.relpath(Path(page).resolve(), Path(out).resolve().parent)
        paragraphs.append(
            "The page below shows the material under a light and from a view that you drag "
            "over the hemisphere (WebGL2, one file, no network; made by btf view). It is "
            "linked, not embedded: this page holds no script.")
        links = ((f"open {Path(page).name}", href),)
    if render is not None:
        path = Path(render)
        if not path.is_file():
            raise BTFError(f"--mitsuba: {render}: no such PNG file")
        data = path.read_bytes()
        made = png_text(data).get("btf", "")
        paragraphs.append("Rendered by Mitsuba 3 through btf's BSDF plugin (btf mitsuba), as "
                          "any scene that names it renders the material" + (f": {made}."
                                                                            if made else "."))
        pictures = (Picture(str(path), data),)
    title = "Relight it" if page is not None else "Rendered by Mitsuba 3"
    return Section(title, tuple(paragraphs), pictures=pictures, links=links)


def report(params: ReportParams, session: Session) -> Path:
    """Write the page (see the module)."""
    import json

    start = time.perf_counter()
    history = _history(session, params.out)
    sections = [s for s in [_stages(history)] if s is not None]
    if params.compressed:
        session.log(f"report: compression of {params.compressed}")
        sections.append(_compression(params.compressed, params))
    if params.enlarged:
        session.log(f"report: enlargement {params.enlarged}"
                    + (f" against {params.truth}" if params.truth else ""))
        sections.append(_enlargement(params.enlarged, params))
    if params.tiles:
        sections.append(_tiles(params.tiles))
    if params.pictures:
        sections.append(_pictures(params.pictures))
    if params.viewer or params.mitsuba:
        sections.append(_viewer(params.viewer, params.out, params.mitsuba))
    page = render(params.title, f"Made by btf {__version__} on "
                  f"{time.strftime('%Y-%m-%d %H:%M')} in {time.perf_counter() - start:.1f} s.",
                  sections)
    write_whole(params.out, page.encode("utf-8"), params.overwrite)
    if history:
        write_whole(_sidecar(params.out), json.dumps({"history": history}, indent=1).encode(),
                    True)
    session.log(f"report: {len(sections)} section(s) -> {params.out}")
    return Path(params.out)


STAGE = Stage("report", ReportParams, report,
              "write one self-contained HTML page of a run's results",
              "Write one HTML page (pictures embedded, no script, no network) of what a run "
              "made and how well: each stage of the btf run it ends with (time, peak memory, "
              "the command that reproduces it); compression rank, size ratio and error; an "
              "enlargement against ground truth and the tiling and per-texel lookup "
              "baselines, side by side for a few lights; a tile set's border figures; and any "
              "PNG pictures (a rendered surface, a scene's images).")
