"""The stages a run config or the command line can call, by name."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pipeline.compress import CompressParams, compress
from pipeline.export import ExportParams, PreviewParams, export, preview
from pipeline.generate import GenerateParams, generate
from pipeline.ingest import IngestParams, ingest
from pipeline.inspect import InspectParams, inspect
from pipeline.reconstruct import ReconstructParams, reconstruct


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
        Stage("generate", GenerateParams, generate,
              "render a procedural BTF with ground truth into a store",
              "Render a procedural material (or a photo with --albedo) under a direction "
              "sampling, tile by tile, straight into a radiance store. The store also holds "
              "the ground-truth height, albedo, roughness and specular fields. The same "
              "arguments give a bit-identical store on every scheduler.", makes_store=True),
        Stage("ingest", IngestParams, ingest,
              "read a folder of EXR/PNG layers into a store",
              "Read EXR or PNG layers into a radiance store. Directions come from a manifest "
              "CSV (file,theta_light,phi_light,theta_view,phi_view; SRC/manifest.csv is used "
              "when present) or from UTIA names tl{theta}_pl{phi}_tv{theta}_pv{phi}.exr. "
              "Images are streamed a block of directions at a time.", makes_store=True),
        Stage("export", ExportParams, export,
              "write layers of a store as EXR or PNG files",
              "Write the selected layers as EXR (exact float32, or --half) or tone-mapped PNG, "
              "named by their directions, with a manifest.csv that btf ingest reads back."),
        Stage("preview", PreviewParams, preview,
              "draw a contact sheet of a spread of directions",
              "Draw a contact sheet of layers spread over the directions (farthest-point "
              "sampling), labelled with their angles, all with one exposure."),
        Stage("compress", CompressParams, compress,
              "out-of-core randomized SVD of a store into U, S, V",
              "Factorise the range-reduced BTF matrix log(radiance + eps) (rows: view x light x "
              "channel textures, columns: texels) as U S V^T with a randomized SVD that streams "
              "the store in row blocks: power iterations + 1 passes (each A^T A fused into one "
              "pass), or one pass with --passes 1. The relative error comes from an exact "
              "identity (or, for one pass, an error sketch); --verify adds a pass for the "
              "average ABRDF RMSE in linear radiance. Memory: a few row blocks and sketches.",
              makes_store=True),
        Stage("reconstruct", ReconstructParams, reconstruct,
              "rebuild chosen layers, region and rank from a compressed store",
              "Rebuild exactly the requested layers (--light, --view), texel region (--region) "
              "and rank (--rank) as exp(U S V^T) - eps, reading only the U chunks and V tiles "
              "they need, into a radiance store or EXR files (--format exr)."),
        Stage("inspect", InspectParams, inspect,
              "describe a store (metadata; --scan reads the data)",
              "Describe a store from its metadata: kind, variables, dims, dtypes, chunks, "
              "codecs, bytes in memory and on disk, direction sampling and provenance. --scan "
              "reads the data chunk by chunk for min/max/mean and NaN/Inf/negative counts."),
    )
}
