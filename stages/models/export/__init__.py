"""`goi export-model`: local Hugging Face checkpoints -> one model bundle (docs/models.md).

Each SOURCE is a checkpoint directory, recognised by its config.json (safetensors weights only):
- a CLIP checkpoint: a dense MaskCLIP image encoder and the text encoder (`clip`);
- a sentence-transformers checkpoint (modules.json): a text encoder (`sentence`);
- a CLIPSeg checkpoint: a RES split into `clipseg_image.onnx`, `clipseg_text.onnx` and
  `clipseg_decoder.onnx` (`clipseg_split`), or with --clipseg-whole one graph, `res.onnx`
  (`clipseg`);
- an OWLv2 and a SAM checkpoint, together: OWLv2 + SAM, split into an image side and a prompt
  side, `owl_image.onnx`, `owl_text.onnx`, `sam_encoder.onnx`, `sam_decoder.onnx` (`owlv2`);
  a SAM 2 checkpoint (Sam2Model, e.g. SAM 2.1 hiera-tiny) may stand for SAM wherever SAM goes
  (`sam2`);
- a Grounding DINO and a SAM checkpoint, together: a Grounded-SAM RES, `detector.onnx`,
  `sam_encoder.onnx` and `sam_decoder.onnx` (`grounding_dino`, `sam`). In place of the SAM
  checkpoint, a directory holding a SAM already in segment-anything's ONNX layout (no
  config.json; an encoder and a decoder .onnx) is copied in as it is (`sam_onnx`).
A bundle holds at most one encoder source and one RES. Every source is read and checked before
anything is exported (its config, weights' headers and tokenizer, then the model itself is
loaded, refused when a weight it needs is missing, of another shape or of another dtype's kind);
every exported ONNX file is run once with onnxruntime and compared with
torch before the bundle is written (`common`), and the bundle appears complete or not at all.
Needs the optional extra `goi[export]` (transformers).
"""

from __future__ import annotations

import gc
import json
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from schemas import current_version
from stages import __version__
from stages.core.errors import GoiError
from stages.core.files import check_output_name, make_dir
from stages.core.params import FRACTION, Range, check_params
from stages.core.report import SILENT, Report
from stages.models.bundle import MANIFEST, load_bundle
from stages.models.export.common import (
    check_config,
    check_weights,
    checkpoint_json,
    load_model,
    preprocessor,
    tokenizer_json,
    transformers,
)

#: config.json model_type -> what goi makes of the checkpoint.
KINDS = {
    "clip": "clip",
    "grounding-dino": "detector",
    "owlv2": "owl",
    "sam": "sam",
    "sam2": "sam2",
    # SAM 2.1's Hugging Face checkpoints are Sam2VideoModel's (model_type sam2_video); the image
    # model is a subset of it (vision encoder, prompt encoder, mask decoder; the memory modules
    # are not used), so Sam2Model loads them with every weight it has
    "sam2_video": "sam2",
    "clipseg": "clipseg",
}
#: kind -> the transformers class it is loaded with, and its name in messages.
CLASSES = {
    "clip": ("CLIPModel", "CLIP"),
    "sentence": ("AutoModel", "sentence-transformers"),
    "detector": ("GroundingDinoForObjectDetection", "Grounding DINO"),
    "owl": ("Owlv2ForObjectDetection", "OWLv2"),
    "sam": ("SamModel", "SAM"),
    "sam2": ("Sam2Model", "SAM 2"),
    "clipseg": ("CLIPSegForImageSegmentation", "CLIPSeg"),
}
#: kind -> the prefixes of weights its export never runs, which a checkpoint may lack (a
#: sentence-transformers model is pooled from its last hidden states, not by BERT's pooler).
UNUSED = {"sentence": ("pooler.",)}


@dataclass
class ModelExportParams:
    image_size: Annotated[int, Range(ge=0, le=4096)] = 0
    """CLIP only: square input size of the image encoder (a multiple of the patch size); the
    position embeddings are resampled to it. 0: the checkpoint's own size. Larger sizes give
    finer dense features."""
    detector_height: Annotated[int, Range(ge=96, le=2048)] = 600
    """Grounding DINO only: height of the detector's input canvas, fixed at export. Images are
    resized to fit the canvas (aspect kept) and padded; match its shape to your views' (the
    checkpoint's own processor uses a shortest edge of 800; smaller is faster)."""
    detector_width: Annotated[int, Range(ge=96, le=2048)] = 800
    """Grounding DINO only: width of the detector's input canvas, fixed at export."""
    sam_size: Annotated[int, Range(ge=0, le=2048)] = 0
    """SAM only: side of the encoder's square input (a multiple of 16). 0: the checkpoint's own
    (1024). Smaller resamples the position embeddings: faster, but SAM was not trained so.
    SAM 2's input is fixed (its checkpoint's size)."""
    box_threshold: Annotated[float, FRACTION] = 0.3
    """Grounded-SAM and OWLv2 + SAM: a detected box is used when its score (Grounding DINO: its
    best token probability; OWLv2: its class probability) exceeds this (GOI's value for
    Grounding DINO; OWLv2's own examples use 0.1-0.2)."""
    max_boxes: Annotated[int, Range(ge=1, le=100)] = 8
    """Grounded-SAM and OWLv2 + SAM: at most this many boxes per image, the best scoring,
    prompt SAM."""
    mask_threshold: Annotated[float, Range(ge=-50, le=50)] = 0.0
    """Grounded-SAM and OWLv2 + SAM: a pixel is in a box's mask when SAM's mask logit exceeds
    this."""
    clipseg_whole: bool = False
    """CLIPSeg only: export it as one graph (`res.onnx`, the layout before the RES split)
    instead of split into its vision activations, text and conditional-decoder graphs
    (`clipseg`, whose image side the RES index caches; the same masks)."""
    res_threshold: Annotated[float, FRACTION] = 0.4
    """CLIPSeg: a pixel is in the mask when its probability exceeds this."""
    opset: Annotated[int, Range(ge=14, le=23)] = 17
    """ONNX opset version."""


#: The file that marks a directory as a bundle goi made: --force replaces only such a one (a
#: manifest.json alone could be anybody's).
MARKER = ".goi-export-model"


@dataclass
class ModelExportRun:
    out: Path
    """Bundle directory to create."""
    force: bool = False
    """Replace an existing bundle directory."""


@dataclass
class Source:
    path: Path
    kind: str  # clip | sentence | detector | owl | sam | sam2 | sam-onnx | clipseg
    config: dict
    tokenizer: str | None = None  # tokenizer.json text
    modules: list | None = None  # sentence-transformers' modules.json
    tensors: dict[str, tuple[Path, str]] = field(default_factory=dict)  # check_weights
    model: Any = None  # the loaded transformers model, until it is exported

    def load(self) -> None:
        if self.kind == "sam-onnx":  # ONNX graphs, checked by find_pair already
            return
        cls, what = CLASSES[self.kind]
        unused = UNUSED.get(self.kind, ())
        self.model = load_model(getattr(transformers(), cls), self.path, what, self.tensors, unused)

    def take(self) -> Any:
        """The model, handed over once (so the export holds the only reference)."""
        model, self.model = self.model, None
        return model


def _source(path: Path, opts: ModelExportParams) -> Source:
    """What a checkpoint directory is, with its weights and tokenizer checked."""
    from stages.models.export.sam_onnx import find_pair, is_sam_onnx

    src = Path(path)
    if not src.is_dir():
        raise GoiError(f"SOURCE: {src} is not a checkpoint directory")
    if is_sam_onnx(src):
        size = find_pair(src)[2]  # the layout is checked before anything is exported
        if opts.sam_size and opts.sam_size != size:
            raise GoiError(
                f"--sam-size: {src} is an ONNX SAM fixed at {size}; it cannot be resized"
            )
        return Source(src, "sam-onnx", {})
    cfg = checkpoint_json(src / "config.json")
    if not isinstance(cfg, dict):
        raise GoiError(f"{src / 'config.json'}: expected a JSON object")
    model_type = cfg.get("model_type")
    modules = None
    if model_type in KINDS:
        kind = KINDS[model_type]
    elif (src / "modules.json").is_file():
        kind, modules = "sentence", checkpoint_json(src / "modules.json")
        if not isinstance(modules, list):
            raise GoiError(f"{src / 'modules.json'}: expected a JSON list")
    else:
        raise GoiError(
            f"{src / 'config.json'}: model_type {model_type!r} is not one goi exports: CLIP, a "
            "sentence-transformers model (modules.json), Grounding DINO, OWLv2, SAM, SAM 2 or "
            "CLIPSeg"
        )
    # what builds the model and what feeds it, checked before anything is built
    check_config(cfg, src / "config.json", str(model_type))
    preprocessor(src)
    s = Source(src, kind, cfg, modules=modules, tensors=check_weights(src, cfg))
    if kind == "sam" and opts.sam_size:
        patch = int((cfg.get("vision_config") or {}).get("patch_size", 16))
        if opts.sam_size % patch:
            raise GoiError(f"--sam-size: {opts.sam_size} is not a multiple of {patch}")
    if kind == "sam2" and opts.sam_size:
        from stages.models.export.sam2 import input_size

        if opts.sam_size != input_size(cfg):
            raise GoiError(
                f"--sam-size: {src} is a SAM 2 checkpoint, whose input is fixed at "
                f"{input_size(cfg)}; leave --sam-size out"
            )
    if kind not in ("sam", "sam2"):
        s.tokenizer = tokenizer_json(src)
    return s


def _plan(sources: list[Source]) -> dict[str, Source]:
    """The sources by role; at most one encoder and one RES, and a detector goes with SAM."""
    by_kind: dict[str, Source] = {}
    for s in sources:
        role = {"clip": "encoder", "sentence": "encoder", "sam-onnx": "sam", "sam2": "sam"}.get(
            s.kind, s.kind
        )
        if role in by_kind:
            raise GoiError(
                f"SOURCE: {by_kind[role].path} and {s.path} are both {role} checkpoints; a "
                "bundle holds one"
            )
        by_kind[role] = s
    res = [r for r in ("clipseg", "detector", "owl") if r in by_kind]
    if len(res) > 1:
        raise GoiError(
            "SOURCE: a bundle has one RES: CLIPSeg, Grounding DINO + SAM or OWLv2 + SAM, not "
            f"{' and '.join(by_kind[r].path.name for r in res)}"
        )
    detector = next((r for r in ("detector", "owl") if r in by_kind), None)
    if detector is not None and "sam" not in by_kind:
        raise GoiError(
            f"SOURCE: {by_kind[detector].path} alone makes no RES; a detector needs a SAM "
            "checkpoint (or a SAM ONNX directory) too"
        )
    if "sam" in by_kind and detector is None and res:
        raise GoiError(
            f"SOURCE: a bundle has one RES or SAM: {by_kind[res[0]].path.name} and "
            f"{by_kind['sam'].path.name} go in two bundles (a SAM with no detector is a SAM "
            "alone, for clicks and boxes)"
        )
    return by_kind


def _check_out(out: Path, sources: list[Source], force: bool) -> None:
    for s in sources:
        if out.resolve() == s.path.resolve() or s.path.resolve().is_relative_to(out.resolve()):
            raise GoiError(f"--out: {out} holds the checkpoint {s.path}; choose another directory")
    if out.exists() and not force:
        raise GoiError(f"--out: {out} already exists; pass --force to replace the bundle")
    if out.exists() and not out.is_dir():
        raise GoiError(f"--out: {out} is a file; a bundle is a directory")
    if out.is_symlink():
        raise GoiError(f"--out: {out} is a symbolic link; give the bundle directory itself")
    check_output_name(out, "--out")
    parent = out.parent if str(out.parent) else Path(".")
    if parent.is_dir():  # the bundle is made beside --out: can it be? (not in /proc, say)
        try:
            tempfile.TemporaryDirectory(dir=parent, prefix=f".{out.name}.").cleanup()
        except OSError as e:
            raise GoiError(f"--out: {out}: cannot write in {parent} ({e.strerror or e})") from None
    if out.exists() and any(out.iterdir()) and not (out / MARKER).is_file():
        raise GoiError(
            f"--out: {out} is not a bundle goi export-model made (it has no {MARKER}); goi "
            "replaces only its own bundles: remove it yourself, or choose another directory"
        )


def _export(plan: dict[str, Source], tmp: Path, opts: ModelExportParams, report: Report) -> dict:
    manifest: dict[str, Any] = {"export_checks": {}}

    def done(part: dict) -> None:
        checks = part.pop("export_checks", {})
        manifest.update(part)
        manifest["export_checks"].update(checks)
        for name, c in checks.items():
            report.log(
                f"{name}: checked against torch (largest difference {c['max_abs_error']:.1e}, "
                f"outputs up to {c['max_abs_output']:.3g})"
            )
        gc.collect()  # one model in memory at a time

    enc = plan.get("encoder")
    if enc is not None and enc.kind == "clip":
        from stages.models.export.clip import export_clip

        assert enc.tokenizer is not None
        done(export_clip(enc.take(), enc.path, tmp, enc.tokenizer, opts.image_size, opts.opset))
    elif enc is not None:
        from stages.models.export.sentence import export_sentence

        assert enc.tokenizer is not None and enc.modules is not None
        done(export_sentence(enc.take(), enc.path, tmp, enc.tokenizer, enc.modules, opts.opset))
    if "clipseg" in plan:
        from stages.models.export.clipseg import export_clipseg
        from stages.models.export.clipseg_split import export_clipseg_split

        s = plan["clipseg"]
        assert s.tokenizer is not None
        thr = opts.res_threshold
        how = export_clipseg if opts.clipseg_whole else export_clipseg_split
        done(how(s.take(), s.path, tmp, s.tokenizer, thr, opts.opset))
    if "sam" in plan and "detector" not in plan and "owl" not in plan:
        # a SAM alone: clicks and boxes (goi select --click/--box), no text
        enc_spec, dec_spec, sam_checks = _export_sam(plan["sam"], tmp, opts)
        done({"sam": {"sam_encoder": enc_spec, "sam_decoder": dec_spec},
              "export_checks": sam_checks})  # fmt: skip
    if "detector" in plan or "owl" in plan:
        from stages.models.export.grounding_dino import export_detector
        from stages.models.export.owlv2 import export_owlv2

        d, s = plan.get("detector") or plan["owl"], plan["sam"]
        assert d.tokenizer is not None
        if d.kind == "owl":
            owl, owl_checks = export_owlv2(d.take(), d.path, tmp, d.tokenizer, opts.opset)
            done({"export_checks": owl_checks})
        else:
            canvas = (opts.detector_height, opts.detector_width)
            det, det_check = export_detector(d.take(), d.path, tmp, d.tokenizer, canvas, opts.opset)
            done({"export_checks": {"detector.onnx": det_check}})
        enc_spec, dec_spec, sam_checks = _export_sam(s, tmp, opts)
        common = {
            "sam_encoder": enc_spec,
            "sam_decoder": dec_spec,
            "box_threshold": opts.box_threshold,
            "mask_threshold": opts.mask_threshold,
            "max_boxes": opts.max_boxes,
        }
        if d.kind == "owl":
            section = {"owl_sam": {"image": owl["image"], "text": owl["text"], **common}}
        else:
            section = {"grounded": {"detector": det, **common}}
        done({**section, "export_checks": sam_checks})
    return manifest


def _export_sam(s: Source, tmp: Path, opts: ModelExportParams) -> tuple[dict, dict, dict]:
    """The SAM source into the bundle: (sam_encoder, sam_decoder, export checks)."""
    if s.kind == "sam-onnx":
        from stages.models.export.sam_onnx import import_sam_onnx

        enc_spec, dec_spec = import_sam_onnx(s.path, tmp)
        return enc_spec, dec_spec, {}
    if s.kind == "sam2":
        from stages.models.export.sam2 import export_sam2

        return export_sam2(s.take(), s.path, tmp, opts.opset)
    from stages.models.export.sam import export_sam

    return export_sam(s.take(), s.path, tmp, opts.sam_size, opts.opset)


def export_model(
    sources: Path | Sequence[Path],
    opts: ModelExportParams,
    run: ModelExportRun,
    report: Report = SILENT,
) -> Path:
    """Write one bundle directory from the checkpoints `sources`; returns its path."""
    check_params(opts)
    paths = [Path(sources)] if isinstance(sources, str | Path) else [Path(p) for p in sources]
    if not paths:
        raise GoiError("SOURCE: give at least one checkpoint directory")
    checked = [_source(p, opts) for p in paths]
    plan = _plan(checked)
    out = Path(run.out)
    _check_out(out, checked, run.force)
    for s in checked:  # a checkpoint that is not what its config says fails here, before exports
        s.load()
    make_dir(out.parent, "--out")
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as t:
        tmp = Path(t)
        parts = _export(plan, tmp, opts, report)
        name = "+".join(s.path.resolve().name for s in checked)
        manifest = {
            "schema": "goi.bundle",
            "schema_version": current_version("goi.bundle"),
            "name": name,
            **parts,
        }
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        (tmp / MARKER).write_text(f"written by goi export-model (goi {__version__})\n")
        bundle = load_bundle(tmp)  # what we wrote must pass our own reader
        if bundle.has_res:
            bundle.check_res()
        del bundle
        tmp.chmod(0o755)  # TemporaryDirectory makes it private
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
        tmp.mkdir()  # TemporaryDirectory removes its path on exit
    return out
