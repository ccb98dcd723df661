"""The stages a run config or the command line can call, by name: one module per subcommand.

Each module holds its parameters (a frozen dataclass, :mod:`pipeline.params`) and one function
that opens the inputs, builds its graph (:mod:`pipeline.graphs`) with kernels of :mod:`tasks`,
computes it on the session and writes the output store (:mod:`pipeline.stores`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pipeline.stages import (
    compress,
    crop,
    enlarge,
    export,
    fit,
    generate,
    ingest,
    inspect,
    preview,
    pyramid,
    quilt,
    reconstruct,
    reference,
    render,
    report,
    roller,
    scene,
)


@dataclass(frozen=True)
class Stage:
    """A stage: its parameter class, its function, and the help texts of its subcommand."""

    name: str
    params: type
    run: Callable[[Any, Any], Any]
    summary: str
    description: str
    makes_store: bool = False  # output is a store whose provenance can prove it up to date


STAGES: dict[str, Stage] = {
    stage.name: stage
    for stage in (
        Stage("generate", generate.GenerateParams, generate.generate,
              "render a procedural BTF with ground truth into a store",
              "Render a procedural material (or a photo with --albedo) under a direction "
              "sampling, tile by tile, straight into a radiance store. The store also holds "
              "the ground-truth height, albedo, roughness and specular fields. The same "
              "arguments give a bit-identical store on every scheduler.", makes_store=True),
        Stage("ingest", ingest.IngestParams, ingest.ingest,
              "read measured BTFs (folders, zip archives, BIG, Bonn .btf) into a store",
              "Read a measured BTF into a store; the format comes from SRC. A folder of EXR or "
              "PNG layers (directions from a manifest CSV file,theta_light,phi_light,theta_view,"
              "phi_view, SRC/manifest.csv when present, or UTIA names tl{theta}_pl{phi}_tv"
              "{theta}_pv{phi}.exr, also a folder per view), a Bonn UBO2003/ATRIUM .zip archive "
              "of JPEG or RGBE images (read from the zip), or a UTIA .big file becomes a "
              "radiance store, streamed a block of directions at a time. A Bonn UBO2014 .btf "
              "(DFMF) file becomes a compressed store without expansion: its factors, exactly, "
              "with its colour model. See docs/formats.md.", makes_store=True),
        Stage("export", export.ExportParams, export.export,
              "write layers as EXR/PNG files, or a compressed store as a Bonn .btf file",
              "Write the selected layers of a radiance or compressed store as EXR (exact "
              "float32, or --half) or tone-mapped PNG, named by their directions, with a "
              "manifest.csv that btf ingest reads back. An OUT ending in .btf gets a compressed "
              "store as a Bonn DFMF file for renderers (btflib, btf-extractor, Mitsuba's BTF "
              "plugin): each channel at its own rank, float32 (exact) or --half."),
        Stage("preview", preview.PreviewParams, preview.preview,
              "draw a contact sheet of a spread of directions",
              "Draw a contact sheet of layers spread over the directions (farthest-point "
              "sampling), labelled with their angles, all with one exposure."),
        Stage("crop", crop.CropParams, crop.crop,
              "cut a region and some layers of a radiance store into a new store",
              "Write a texel region (--region Y0:Y1,X0:X1) and optionally some lights "
              "(--light) and views (--view) of a radiance store as a new radiance store, "
              "streamed block by block; ground-truth fields of a generated store are cut "
              "along. For samples, constraint photos and ground-truth regions.",
              makes_store=True),
        Stage("compress", compress.CompressParams, compress.compress,
              "out-of-core randomized SVD of a store into U, S, V",
              "Factorise the range-reduced BTF matrix log(radiance + eps) (rows: view x light x "
              "channel textures, columns: texels) as U S V^T with a randomized SVD that streams "
              "the store in row blocks: power iterations + 1 passes (each A^T A fused into one "
              "pass), or one read with --passes 1 (a one-view sketch by texel tiles, its co-range "
              "sketch kept in a scratch array that is removed at the end). The relative error "
              "comes from an exact identity (or, for one pass, an error sketch); --verify adds "
              "a pass for the average ABRDF RMSE in linear radiance. Memory: a few blocks and "
              "sketches; with --sketch rows or --passes 1 nothing grows with the texels.",
              makes_store=True),
        Stage("reconstruct", reconstruct.ReconstructParams, reconstruct.reconstruct,
              "rebuild chosen layers, region and rank from a compressed store",
              "Rebuild exactly the requested layers (--light, --view), texel region (--region) "
              "and rank (--rank) as exp(U S V^T) - eps, reading only the U chunks and V tiles "
              "they need, into a radiance store or EXR files (--format exr)."),
        Stage("enlarge", enlarge.EnlargeParams, enlarge.enlarge_stage,
              "a large BTF from a small compressed sample and full-size photos (paper 000)",
              "Synthesize the eigentextures of a BTF at the size of the constraint photos from "
              "a compressed sample (its eigen-ABRDFs stay): Texture Optimization guided by the "
              "photos (multi-level EM, PCA-reduced exact search), statistical synthesis on a "
              "steerable pyramid, and a per-texel QP that makes the result reproduce the "
              "photos, alternated until the change is below --tol. Each photo layer is matched "
              "to the sample's nearest direction; the sample's place in the photos is found "
              "by normalised cross-correlation unless --sample-origin gives it. The output is "
              "a compressed store that btf reconstruct, quilt, roller and inspect take.",
              makes_store=True),
        Stage("reference", reference.ReferenceParams, reference.reference,
              "write the reference image that guides quilting (paper 003, 2.2)",
              "Compute, from all layers of the view closest to the normal, the diffuse map, "
              "a normal map from the strongest response per texel, the height map integrated "
              "from it (Frankot-Chellappa), a reflectance map from two normal estimates with "
              "different exponents, and their weighted combination; write them as one EXR."),
        Stage("quilt", quilt.QuiltStageParams, quilt.quilt,
              "plan a seamless tile set on the reference image and apply it to every layer",
              "Periodic image quilting planned on the reference image (paper 003: corners, "
              "edges, interior; K best candidates by masked SSD; cyclic minimum-error boundary "
              "cut with border flags; Gaussian-blurred blending) for V corner types (V^4 "
              "tiles; V=1: one periodic texture). The plan compiles to one sparse "
              "prescription per tile, stored, and applied identically to every layer (or to "
              "the eigentextures of a compressed store).", makes_store=True),
        Stage("roller", roller.RollerStageParams, roller.roller,
              "detect the periodicity lattice and build double toroidal tiles (paper 004)",
              "Detect the two periodicity vectors u, v (any direction) of the perpendicularly "
              "lit layer from its Fourier spectrum and autocorrelation (--detect-only prints "
              "them; --json as one object). Otherwise cut a tile spanned by whole periods "
              "along the cheapest paths through the overlap error (scipy's Dijkstra) so it "
              "repeats seamlessly on the lattice, optionally N tiles with identical borders "
              "(--tiles), and apply it to every layer (or to the eigentextures of a "
              "compressed store). btf render lays the tiles on surfaces of any size.",
              makes_store=True),
        Stage("render", render.RenderParams, render.render,
              "render one layer of a surface of any size from a tile set",
              "Render one layer (--light, --view) of an unbounded surface covered by a tile "
              "set, over a region of any size (--size, --origin): each tile is chosen by a hash "
              "of its lattice position and --seed so corners always match, and only that layer "
              "of the tile set is read. EXR, tone-mapped PNG, or .zarr written block by block."),
        Stage("fit", fit.FitParams, fit.fit,
              "fit an ABTF in HLS: constant hue/saturation, lightness per rotation",
              "HLS fitting (paper 003, 2.5): per texel, hue and saturation constant over the "
              "lights and lightness fitted, for every light rotation, by six parameters over "
              "elevation. Reports the fit error (RMSE and maximum, linear RGB) and the size "
              "ratio; the fitted store rebuilds radiance lazily.", makes_store=True),
        Stage("pyramid", pyramid.PyramidParams, pyramid.pyramid,
              "add levels of detail (OME-NGFF multiscales) to a store",
              "Add levels of detail to a radiance, compressed or quilted tile-set store (of its "
              "tiles, whose sides must be multiples of 2^n): level n is the mean of "
              "2^n x 2^n texel blocks of level 0 in linear radiance (for a compressed store, "
              "projected back on U; --method mean-v averages V instead, a log-domain "
              "approximation), chunked like level 0, stored under pyramid/N/ and listed in an "
              "OME-NGFF-style 'multiscales' attribute. btf inspect lists them."),
        Stage("report", report.ReportParams, report.report,
              "write one self-contained HTML page of a run's results",
              "Write one HTML page (pictures embedded, no script, no network) of what a run "
              "made and how well: each stage of the btf run it ends with (time, peak memory, "
              "the command that reproduces it); compression rank, size ratio and error; an "
              "enlargement against ground truth and the tiling and per-texel lookup "
              "baselines, side by side for a few lights; a tile set's border figures; and any "
              "PNG pictures (a rendered surface, a scene's images)."),
        Stage("scene", scene.SceneParams, scene.scene_stage,
              "compute only what a scene needs: directions, region, level, rank",
              "Write exactly what a scene spec (YAML, see configs/scenes/) asks of a store: "
              "its light/view directions (measured or not: nearest or barycentric "
              "interpolation over the measured ones), its texel region (a tile set: a surface "
              "of any size at an origin), a level of detail (the store's pyramid level, or "
              "block means of level 0 computed on the fly) and, for compressed sources, a "
              "rank. Only the chunks the scene touches are read; the counts are logged and "
              "recorded. Output: a .zarr store, or a folder of EXR or PNG images."),
        Stage("inspect", inspect.InspectParams, inspect.inspect,
              "describe a store (metadata; --scan reads the data)",
              "Describe a store from its metadata: kind, variables, dims, dtypes, chunks, "
              "codecs, bytes in memory and on disk, direction sampling and provenance. --scan "
              "reads the data chunk by chunk for min/max/mean and NaN/Inf/negative counts."),
    )
}
