"""Hostile inputs, fourth sweep (docs/reliability.md): the lifted mode, model bundles,
export-model, the blend cache's partial files, two runs of one output, eval and demo.

Each case goes through the real CLI and must give exit 2, one `goi: error:` line naming the
file, field or option, no traceback, and leave every byte of its inputs and of the place it
writes to as it was (the same assertions as test_hostile_inputs.py). Beside the table: the
outcomes that are not a refusal (a forged partial cache is rebuilt, never reused; a lock left
by a killed run is taken over) and two concurrent fits of one output."""

import json
import os
import shutil
import subprocess
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from goi_cli.main import main
from tests.robustness.test_hostile_inputs import (
    _copy,
    _digest,
    _eval_room,
    _field,
    _query,
    _render,
    _select,
    assert_refused,
    world,  # noqa: F401  (the shared fixture)
)

ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Case:
    name: str
    make: Callable  # (world, tmp) -> argv; may write broken inputs into tmp
    words: tuple[str, ...]
    subprocess: bool = False  # run in a child: C-level stderr (onnxruntime's log) shows there
    absent: tuple[str, ...] = ()  # words the message must not hold


# --- the blend cache's partial file and the output lock ------------------------------------


def _cache_partial(make_it: Callable[[Path, dict, Path], None]):
    """fit-field with `<tmp>/blend_cache.h5.partial` made by `make_it(partial, world, tmp)`."""

    def make(s, tmp):
        make_it(tmp / "blend_cache.h5.partial", s, tmp)
        return _field(s, tmp)

    return make


def _link_to(target: Callable[[dict, Path], Path], hard: bool = False):
    def make_it(partial: Path, s, tmp):
        t = target(s, tmp)
        os.link(t, partial) if hard else partial.symlink_to(t)

    return make_it


def _user_file(s, tmp) -> Path:
    f = tmp / "notes.txt"
    f.write_text("the user's own file\n")
    return f


def _extract_partial(make_it: Callable[[Path, dict, Path], None]):
    def make(s, tmp):
        make_it(tmp / "o.h5.partial", s, tmp)
        return ["extract", "--scene", str(s["scene"]), "--from", str(s["features"]),
                "--out", str(tmp / "o.h5")]  # fmt: skip

    return make


def _held_lock(name: str, make_argv: Callable):
    """Another run (this test process, pid 424242 written in the file) holds `<tmp>/<name>`."""
    import fcntl

    held = []

    def make(s, tmp):
        lock = tmp / name
        fd = os.open(lock, os.O_RDWR | os.O_CREAT)
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.write(fd, b"424242\n")
        held.append(fd)  # closed (released) by the fixture-less test's garbage: see _run
        return make_argv(s, tmp)

    make.held = held  # type: ignore[attr-defined]
    return make


# --- bundles -------------------------------------------------------------------------------

DIM = 16  # the shared world's feature dimension: only the checked value can stop a case
VOCAB = ["[UNK]", "red", "chair", "the", "green", "sofa", "box"]


def _export(model, args, path, inputs, outputs, axes):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, args, str(path), input_names=inputs, output_names=outputs,
                          dynamic_axes=axes, dynamo=False)  # fmt: skip


class _Text(torch.nn.Module):
    def __init__(self, vocab: int, fill: float | None = None):
        super().__init__()
        self.emb = torch.nn.Embedding(vocab, 8)
        self.proj = torch.nn.Linear(8, DIM)
        if fill is not None:  # a broken encoder: every output this value
            with torch.no_grad():
                self.proj.weight.zero_()
                self.proj.bias.fill_(fill)

    def forward(self, input_ids):
        return self.proj(self.emb(input_ids).mean(1))


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A tiny bundle: an image encoder (a 4x4 convolution) and a text encoder; and the same
    text encoder exported three more ways (zero output, NaN output, fewer embeddings than
    the tokenizer's words)."""
    from tokenizers import Tokenizer, models, pre_tokenizers

    root = tmp_path_factory.mktemp("bundle3")
    b = root / "b"
    b.mkdir()
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(3, DIM, 4, stride=4).eval()
    _export(conv, (torch.randn(1, 3, 32, 32),), b / "image_encoder.onnx", ["image"],
            ["features"], {"image": {2: "h", 3: "w"}})  # fmt: skip
    ids = (torch.zeros(1, 3, dtype=torch.int64),)
    axes = {"input_ids": {1: "n"}}
    for name, model in (("text_encoder", _Text(len(VOCAB))), ("zero", _Text(len(VOCAB), 0.0)),
                        ("nan", _Text(len(VOCAB), float("nan"))), ("short", _Text(2))):  # fmt: skip
        _export(model.eval(), ids, b / f"{name}.onnx", ["input_ids"], ["text_embeds"], axes)
    tok = Tokenizer(models.WordLevel({w: i for i, w in enumerate(VOCAB)}, unk_token="[UNK]"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.save(str(b / "tokenizer.json"))
    manifest = {
        "schema": "goi.bundle", "schema_version": "1.1", "name": "tiny", "feature_dim": DIM,
        "image_encoder": {"file": "image_encoder.onnx", "input": "image", "output": "features",
                          "mean": [0.5, 0.5, 0.5], "std": [0.25, 0.25, 0.25],
                          "channel_order": "RGB"},
        "text_encoder": {"file": "text_encoder.onnx", "input_ids": "input_ids",
                         "output": "text_embeds",
                         "tokenizer": {"kind": "huggingface", "file": "tokenizer.json",
                                       "max_length": 16}},
    }  # fmt: skip
    (b / "manifest.json").write_text(json.dumps(manifest))
    return b, manifest


def _bundle_copy(edit: Callable[[dict, Path], None], command: str = "extract"):
    """A command run with a copy of the tiny bundle whose manifest `edit` changed: extract
    (image encoder) or query (text encoder, with the RES masks as files)."""

    def make(s, tmp):
        b = _copy(s["bundle"][0], tmp / "b")
        m = json.loads(json.dumps(s["bundle"][1]))
        edit(m, b)
        (b / "manifest.json").write_text(json.dumps(m))
        if command == "extract":
            return ["extract", "--scene", str(s["scene"]), "--bundle", str(b),
                    "--out", str(tmp / "o.h5")]  # fmt: skip
        if command == "extract-images":  # a scene with its images: the encoder runs
            import cv2

            d = _copy(s["scene"], tmp / "scene")
            (d / "images").mkdir()
            for name, cam in s["cameras"].items():
                cv2.imwrite(str(d / "images" / f"{name}.png"),
                            np.zeros((cam.height, cam.width, 3), np.uint8))  # fmt: skip
            return ["extract", "--scene", str(d), "--bundle", str(b), "--out", str(tmp / "o.h5")]
        return ["query", "--scene", str(s["scene"]), "--field", str(s["w"] / "field.h5"),
                "--prompt", "the box", "--bundle", str(b), "--res-masks", str(s["w"] / "res"),
                "--out", str(tmp / "q")]  # fmt: skip

    return make


def _set(path: str, value):
    def edit(m: dict, b: Path):
        *head, last = path.split(".")
        d = m
        for k in head:
            d = d[k]
        d[last] = value

    return edit


def _grounded(edit: Callable[[dict], None]):
    """A RES-only grounded bundle (model files are placeholders: the manifest is refused
    before any of them is opened), used by query for its RES masks."""

    def make(s, tmp):
        b = tmp / "g"
        b.mkdir()
        for f in ("detector.onnx", "sam_encoder.onnx", "sam_decoder.onnx", "tokenizer.json"):
            (b / f).write_bytes(b"placeholder")
        stats = {"mean": [0.5, 0.5, 0.5], "std": [0.25, 0.25, 0.25]}
        g = {
            "detector": {"file": "detector.onnx", "pixel_values": "pixel_values",
                         "pixel_mask": "pixel_mask", "input_ids": "input_ids",
                         "attention_mask": "attention_mask", "logits": "logits",
                         "boxes": "pred_boxes", "size": [128, 96], **stats,
                         "tokenizer": {"kind": "huggingface", "file": "tokenizer.json",
                                       "max_length": 32}},
            "sam_encoder": {"file": "sam_encoder.onnx", "input": "pixel_values",
                            "output": "image_embeddings", "size": [128, 128], **stats},
            "sam_decoder": {"file": "sam_decoder.onnx", "image_embeddings": "image_embeddings",
                            "boxes": "input_boxes", "masks": "pred_masks"},
            "box_threshold": 0.3, "mask_threshold": 0.0, "max_boxes": 4,
        }  # fmt: skip
        m = {"schema": "goi.bundle", "schema_version": "1.1", "name": "g", "grounded": g}
        edit(g)
        (b / "manifest.json").write_text(json.dumps(m))
        return ["query", "--scene", str(s["scene"]), "--field", str(s["w"] / "field.h5"),
                "--prompt", "box", "--text-embeddings", str(s["w"] / "text.json"),
                "--bundle", str(b), "--out", str(tmp / "q")]  # fmt: skip

    return make


def _text_model(name: str):
    return _bundle_copy(_set("text_encoder.file", f"{name}.onnx"), "query")


# --- export-model --------------------------------------------------------------------------


def _checkpoint(write: Callable[[Path], None], *extra: str):
    """export-model of a checkpoint directory (a CLIP config) whose weights `write` makes."""

    def make(s, tmp):
        ck = tmp / "ckpt"
        ck.mkdir()
        (ck / "config.json").write_text(json.dumps({"model_type": "clip"}))
        (ck / "tokenizer.json").write_text("{}")
        write(ck)
        return ["export-model", str(ck), "--out", str(tmp / "bundle"), *extra]

    return make


def _safetensors(header: bytes, body: bytes = b"") -> bytes:
    return len(header).to_bytes(8, "little") + header + body


def _index(shards: dict) -> Callable[[Path], None]:
    def write(ck: Path):
        (ck / "model.safetensors.index.json").write_text(json.dumps({"weight_map": shards}))
        (ck / "pytorch_model.bin").write_bytes(b"\x80\x04 a pickle would be here")
        (ck / "ok.safetensors").write_bytes(_safetensors(b"{}"))

    return write


def _header(obj) -> Callable[[Path], None]:
    body = b"\0" * 16
    return lambda ck: (ck / "model.safetensors").write_bytes(
        _safetensors(json.dumps(obj).encode(), body)
    )


def _export_over(make_dir: Callable[[Path], None]):
    """export-model --force onto a directory goi did not make (the checkpoint is sound
    enough that only --out can stop it)."""

    def make(s, tmp):
        out = tmp / "bundle"
        make_dir(out)
        argv = _checkpoint(_header({}), "--force")(s, tmp)
        return argv

    return make


# --- lifted options, late checks -----------------------------------------------------------


def _lift_plane(s, tmp, *extra, out=None, res=None):
    return ["fit-hyperplane", "--scene", str(s["scene"]), "--field", str(s["w"] / "field.h5"),
            "--prompt", "box", "--text-embeddings", str(s["w"] / "text.json"),
            "--res-masks", str(res or s["w"] / "res"), "--out", str(out or tmp / "p.h5"),
            "--lift", *extra]  # fmt: skip


def _empty_masks(s, tmp):
    import cv2

    res = _copy(s["w"] / "res", tmp / "res")
    for f in res.glob("*.png"):
        cv2.imwrite(str(f), np.zeros_like(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)))
    return _lift_plane(s, tmp, res=res)


def _room_ids(targets):
    """eval on a room with per-Gaussian instance ids, whose prompt names `targets`."""

    def make(s, tmp):
        argv = _eval_room(s, tmp)
        room = tmp / "room"
        np.save(room / "gaussian_ids.npy", s["onehot"].argmax(1).astype(np.int64))
        prompts = json.loads((room / "prompts.json").read_text())
        prompts[0]["targets"] = targets
        (room / "prompts.json").write_text(json.dumps(prompts))
        return argv

    return make


def _demo(tmp, *extra, out=None):
    return ["demo", "--out", str(out or tmp / "demo"), "--iterations", "1", *extra]


def _user_dir(tmp) -> Path:
    d = tmp / "mine"
    d.mkdir()
    (d / "index.html").write_text("<p>my page</p>")
    return d


def _with_dir(make_argv: Callable, setup: Callable[[Path], object]):
    def make(s, tmp):
        setup(tmp)
        return make_argv(s, tmp)

    return make


PROC = "/proc/goi-test-output"

CASES = [
    # partial files
    Case("blend_cache.h5.partial a symlink to the features file (an input)",
         _cache_partial(_link_to(lambda s, t: s["w"] / "f.h5")), ("--cache", "symbolic link")),
    Case("blend_cache.h5.partial a symlink to the user's own file",
         _cache_partial(_link_to(_user_file)), ("--cache", "symbolic link")),
    Case("blend_cache.h5.partial a dangling symlink",
         _cache_partial(lambda p, s, t: p.symlink_to(t / "nowhere")), ("--cache", "symbolic link")),
    Case("blend_cache.h5.partial a hard link to the user's file",
         _cache_partial(_link_to(_user_file, hard=True)), ("--cache", "hard link")),
    Case("blend_cache.h5.partial a FIFO (never opened)",
         _cache_partial(lambda p, s, t: os.mkfifo(p)), ("--cache", "regular file"),
         subprocess=True),
    Case("blend_cache.h5.partial a directory",
         _cache_partial(lambda p, s, t: p.mkdir()), ("--cache", "regular file")),
    Case("extract's <out>.partial a symlink to the scene's cameras.json (an input)",
         _extract_partial(_link_to(lambda s, t: s["scene"] / "cameras.json")),
         ("--out", "o.h5.partial", "inputs")),
    Case("extract's <out>.partial a symlink to the user's file",
         _extract_partial(_link_to(_user_file)), ("--out", "symbolic link")),
    Case("extract's <out>.partial a hard link to the user's file",
         _extract_partial(_link_to(_user_file, hard=True)), ("--out", "hard link")),
    # one run per output
    Case("fit-field while another run holds --out",
         _held_lock("field.h5.lock", lambda s, t: _field(s, t)), ("--out", "another goi run",
                                                                  "424242")),
    Case("fit-field while another run holds the blend cache",
         _held_lock("blend_cache.h5.lock", lambda s, t: _field(s, t, out=t / "other.h5")),
         ("--cache", "another goi run", "424242")),
    Case("extract while another run holds --out",
         _held_lock("o.h5.lock", _extract_partial(lambda p, s, t: None)),
         ("--out", "another goi run", "424242")),
    Case("fit-field whose <out>.lock is a symlink",
         lambda s, t: ((t / "field.h5.lock").symlink_to(_user_file(s, t)), _field(s, t))[1],
         ("--out", "lock")),
    # manifest values (extract: the image encoder; query: the text encoder)
    Case("image size [200000, 200000]", _bundle_copy(_set("image_encoder.size", [200000] * 2)),
         ("manifest.json", "'image_encoder.size'", "4096")),
    Case("image size [true, 32]", _bundle_copy(_set("image_encoder.size", [True, 32])),
         ("manifest.json", "'image_encoder.size'", "integers")),
    Case("image size ['32', 32]", _bundle_copy(_set("image_encoder.size", ["32", 32])),
         ("manifest.json", "'image_encoder.size'")),
    Case("image size [0, 32]", _bundle_copy(_set("image_encoder.size", [0, 32])),
         ("'image_encoder.size'",)),
    Case("mean ['0.5', 0.5, 0.5]", _bundle_copy(_set("image_encoder.mean", ["0.5", 0.5, 0.5])),
         ("'image_encoder.mean'", "finite numbers")),
    Case("mean 1e400 (parsed as inf)",
         lambda s, t: _raw_manifest(s, t, '"mean": [1e400, 0.5, 0.5]'),
         ("'image_encoder.mean'", "finite")),
    Case("mean [5, 0.5, 0.5] (of a 0..1 image)",
         _bundle_copy(_set("image_encoder.mean", [5, 0.5, 0.5])), ("'image_encoder.mean'",)),
    Case("std [0, 0, 0]", _bundle_copy(_set("image_encoder.std", [0, 0, 0])),
         ("'image_encoder.std'",)),
    Case("std [true, 1, 1]", _bundle_copy(_set("image_encoder.std", [True, 1, 1])),
         ("'image_encoder.std'",)),
    Case("std [1e-30, ...] (its inputs would overflow)",
         _bundle_copy(_set("image_encoder.std", [1e-30] * 3)), ("'image_encoder.std'",)),
    Case("feature_dim 10**30", _bundle_copy(_set("feature_dim", 10**30)),
         ("'feature_dim'",)),
    Case("image_encoder.input ''", _bundle_copy(_set("image_encoder.input", "")),
         ("'image_encoder.input'",)),
    Case("tokenizer max_length true", _bundle_copy(_set("text_encoder.tokenizer.max_length",
                                                        True), "query"),
         ("'text_encoder.tokenizer.max_length'",)),
    Case("tokenizer max_length 10**9",
         _bundle_copy(_set("text_encoder.tokenizer.max_length", 10**9), "query"),
         ("'text_encoder.tokenizer.max_length'", "8192")),
    Case("grounded box_threshold true", _grounded(lambda g: g.update(box_threshold=True)),
         ("'grounded.box_threshold'",)),
    Case("grounded box_threshold 1.5", _grounded(lambda g: g.update(box_threshold=1.5)),
         ("'grounded.box_threshold'",)),
    Case("grounded max_boxes true", _grounded(lambda g: g.update(max_boxes=True)),
         ("'grounded.max_boxes'",)),
    Case("grounded max_boxes 10**6", _grounded(lambda g: g.update(max_boxes=10**6)),
         ("'grounded.max_boxes'",)),
    Case("grounded detector size [100000, 96]",
         _grounded(lambda g: g["detector"].update(size=[100000, 96])),
         ("'grounded.detector.size'",)),
    Case("grounded sam_encoder std ['1', 1, 1]",
         _grounded(lambda g: g["sam_encoder"].update(std=["1", 1, 1])),
         ("'grounded.sam_encoder.std'",)),
    # models that fail or lie while running
    Case("an image encoder that fails at run time (2x2 input to a 4x4 convolution)",
         _bundle_copy(_set("image_encoder.size", [2, 2]), "extract-images"),
         ("image_encoder.onnx", "failed", "'image'"), subprocess=True),
    Case("a text encoder that fails at run time (a token id beyond its embeddings)",
         _text_model("short"), ("short.onnx", "failed", "'input_ids'"), subprocess=True),
    Case("a text encoder returning a zero embedding", _text_model("zero"),
         ("zero.onnx", "zero embedding")),
    Case("a text encoder returning NaN", _text_model("nan"), ("nan.onnx", "NaN")),
    # the safetensors-only promise
    Case("model.safetensors.index.json naming a .bin",
         _checkpoint(_index({"w": "pytorch_model.bin"})),
         ("model.safetensors.index.json", "pytorch_model.bin", "safetensors")),
    Case("an index naming a shard outside the checkpoint",
         _checkpoint(_index({"w": "../ok.safetensors"})),
         ("model.safetensors.index.json", "not a file")),
    Case("an index with an empty weight_map", _checkpoint(_index({})), ("weight_map",)),
    Case("a model.safetensors of random bytes",
         _checkpoint(lambda ck: (ck / "model.safetensors").write_bytes(os.urandom(64))),
         ("model.safetensors", "not a safetensors file")),
    Case("a safetensors header whose length passes the file's end",
         _checkpoint(lambda ck: (ck / "model.safetensors").write_bytes(
             (10**6).to_bytes(8, "little") + b"{}")), ("model.safetensors", "header length")),
    Case("a safetensors header that is not JSON",
         _checkpoint(lambda ck: (ck / "model.safetensors").write_bytes(_safetensors(b"{nope"))),
         ("model.safetensors", "not JSON")),
    Case("a safetensors tensor whose bytes pass the file's end",
         _checkpoint(_header({"w": {"dtype": "F32", "shape": [100], "data_offsets": [0, 400]}})),
         ("model.safetensors", "'w'", "broken header")),
    Case("a safetensors tensor of an unknown dtype",
         _checkpoint(_header({"w": {"dtype": "PICKLE", "shape": [4], "data_offsets": [0, 16]}})),
         ("model.safetensors", "'w'")),
    # export-model --force and demo --out: never a directory goi did not make
    Case("export-model --force onto the user's directory holding a manifest.json",
         _export_over(lambda d: (d.mkdir(), (d / "manifest.json").write_text("{}"),
                                 (d / "thesis.tex").write_text("years of work"))),
         ("--out", "not a bundle goi export-model made")),
    Case("export-model --force onto a symlink to a directory",
         _export_over(lambda d: (d.parent.joinpath("real").mkdir(), d.symlink_to("real"))),
         ("--out", "symbolic link")),
    Case("demo --out a directory of the user's files",
         lambda s, t: _demo(t, out=_user_dir(t)), ("--out", "--force", "index.html")),
    Case("demo --out a file", lambda s, t: (_user_file(s, t), _demo(t, out=t / "notes.txt"))[1],
         ("--out", "is a file")),
    Case("demo --prompts ','", lambda s, t: _demo(t, "--prompts", ","), ("--prompts", "no prompt")),
    Case("demo --prompts UNKNOWN (refused before --out is made)",
         lambda s, t: _demo(t, "--prompts", "p99"), ("--prompts", "p99")),
    # lifted options
    Case("query --lift --confidence-rounds 10**9",
         lambda s, t: _query(s, t, "--lift", "--confidence-rounds", "1000000000"),
         ("--confidence-rounds",)),
    Case("query --lift --fit-on UNKNOWN", lambda s, t: _query(s, t, "--lift", "--fit-on", "v99"),
         ("--fit-on", "--lift")),
    Case("query --lift --fit-views 3", lambda s, t: _query(s, t, "--lift", "--fit-views", "3"),
         ("--fit-views", "--lift")),
    Case("query --min-evidence without --lift", lambda s, t: _query(s, t, "--min-evidence", "5"),
         ("--min-evidence", "--lift")),
    Case("query --background-bias without --lift",
         lambda s, t: _query(s, t, "--background-bias", "0.3"), ("--background-bias", "--lift")),
    Case("query --confidence-rounds without --lift",
         lambda s, t: _query(s, t, "--confidence-rounds", "4"), ("--confidence-rounds", "--lift")),
    Case("select --core-share without --lift",
         lambda s, t: _select(s, t, extra=("--core-share", "0.5")), ("--core-share", "--lift")),
    Case("render-mask --min-evidence without --lift",
         lambda s, t: _render(s, t, extra=("--min-evidence", "3")), ("--min-evidence", "--lift")),
    Case("fit-hyperplane --lift --fit-on a view",
         lambda s, t: _lift_plane(s, t, "--fit-on", s["train"][0]), ("--fit-on", "--lift")),
    Case("fit-hyperplane --lift --out a directory (before lifting)",
         lambda s, t: ((t / "pd").mkdir(), _lift_plane(s, t, out=t / "pd"))[1],
         ("--out", "directory")),
    Case("fit-hyperplane --lift --out another artifact (before lifting)",
         lambda s, t: _lift_plane(s, t, out=_copy(s["w"] / "c.h5", t / "c.h5")),
         ("c.h5", "goi.hyperplanes")),
    Case("fit-hyperplane --lift on masks without a positive pixel", _empty_masks,
         ("res", "all empty")),
    # late checks
    Case("fit-field --max-memory-gib below even the step's share (before the cache is built)",
         lambda s, t: _field(s, t, "--max-memory-gib", "0.0001"),
         ("--max-memory-gib", "KiB"), absent=("0.00 GiB",)),
    Case("eval --res-views beyond the training views (before fitting)",
         lambda s, t: _eval_room(s, t) + ["--res-views", "50"], ("--res-views", "50")),
    Case("eval targets that are not instances of the room", _room_ids([99]),
         ("prompts.json", "99", "instance")),
    Case("eval a prompt with no target in a room with instance ids", _room_ids([]),
         ("prompts.json", "no target")),
    # outputs under /proc
    Case("fit-field --out under /proc", lambda s, t: _field(s, t, out=Path(PROC) / "f.h5"),
         (PROC,)),
    Case("fit-field --cache under /proc",
         lambda s, t: _field(s, t, "--cache", f"{PROC}.h5"), (PROC,)),
    Case("extract --out under /proc",
         lambda s, t: ["extract", "--scene", str(s["scene"]), "--from", str(s["features"]),
                       "--out", f"{PROC}.h5"], (PROC,)),  # fmt: skip
    Case("query --out under /proc", lambda s, t: _query(s, t, out=Path(PROC)), (PROC,)),
    Case("select --out under /proc",
         lambda s, t: [a if a != str(t / "sel.h5") else f"{PROC}.h5" for a in _select(s, t)],
         (PROC,)),
    Case("render-mask --out under /proc",
         lambda s, t: [a if a != str(t / "masks") else PROC for a in _render(s, t)], (PROC,)),
    Case("eval --out under /proc",
         lambda s, t: [a if a != str(t / "r.json") else f"{PROC}.json" for a in _eval_room(s, t)],
         (PROC,)),
    Case("demo --out under /proc", lambda s, t: _demo(t, out=Path(PROC)), (PROC,)),
    Case("export-model --out under /proc",
         lambda s, t: [a if a != str(t / "bundle") else PROC
                       for a in _checkpoint(_header({}))(s, t)],
         ("--out", PROC)),
]  # fmt: skip


def _raw_manifest(s, tmp, stats: str):
    """extract with a manifest whose text holds `stats` verbatim (JSON that json.dumps would
    not write, e.g. 1e400)."""
    argv = _bundle_copy(lambda m, b: None)(s, tmp)
    mf = tmp / "b" / "manifest.json"
    mf.write_text(mf.read_text().replace('"mean": [0.5, 0.5, 0.5]', stats))
    return argv


@pytest.fixture(scope="module")
def world3(world, bundle):  # noqa: F811
    world["bundle"] = bundle
    return world


def _run(case: Case, argv: list[str], capsys) -> tuple[int, str]:
    if not case.subprocess:
        capsys.readouterr()
        code = main(argv)
        return code, capsys.readouterr().err
    done = subprocess.run([sys.executable, "-m", "goi_cli", *argv], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)  # fmt: skip
    return done.returncode, done.stderr


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_hostile_input(case, world3, tmp_path, capsys):
    try:
        argv = case.make(world3, tmp_path)
        before, world_before = _digest(tmp_path), _digest(world3["w"])
        scene_before = _digest(world3["scene"])
        code, err = _run(case, argv, capsys)
    finally:
        for fd in getattr(case.make, "held", []):
            os.close(fd)
        getattr(case.make, "held", []).clear()
    assert_refused(code, err, case.words)
    for w in case.absent:
        assert w not in err, (w, err)
    assert _digest(tmp_path) == before, "the output location or an input changed"
    assert _digest(world3["w"]) == world_before, "an input of the shared world changed"
    assert _digest(world3["scene"]) == scene_before, "the scene changed"


def test_enough_cases():
    assert len(CASES) >= 50


# --- outcomes that are not refusals --------------------------------------------------------


def _cache_datasets(path: Path) -> dict[str, bytes]:
    out = {}
    with h5py.File(path) as f:
        f.visititems(
            lambda n, o: (
                out.__setitem__(n, o[()].tobytes()) if isinstance(o, h5py.Dataset) else None
            )
        )
    return out


def _forge(kind: str):
    def edit(f: h5py.File):
        if kind == "count":
            f.attrs["n_gaussians"] = int(f.attrs["n_gaussians"]) + 5
        elif kind == "order":
            order = f["order"][()]
            del f["order"]
            f["order"] = order[::-1]
        elif kind == "grid":
            v = f["views"][next(iter(f["views"]))]
            v.attrs["width"] = int(v.attrs["width"]) + 1
        elif kind == "ids":
            v = f["views"][next(iter(f["views"]))]
            ids = v["indices"][()]
            ids[:] = 10**6
            del v["indices"]
            v["indices"] = ids

    return edit


@pytest.mark.parametrize("kind", ["count", "order", "grid", "ids"])
def test_a_forged_partial_cache_is_rebuilt_not_reused(kind, world, tmp_path, capsys):  # noqa: F811
    """A `.partial` whose recorded identity is right but whose contents are not this cache's
    (Gaussian count, column order, a view's grid, ids out of range) is rebuilt: the run ends
    with the very cache a clean build makes, and a valid field."""
    clean = tmp_path / "clean"
    clean.mkdir()
    assert main(_field(world, clean)) == 0
    forged = tmp_path / "forged"
    forged.mkdir()
    partial = forged / "blend_cache.h5.partial"
    shutil.copy(clean / "blend_cache.h5", partial)
    with h5py.File(partial, "r+") as f:
        _forge(kind)(f)
    capsys.readouterr()
    assert main(_field(world, forged)) == 0
    assert "building the cache again" in capsys.readouterr().err
    assert _cache_datasets(forged / "blend_cache.h5") == _cache_datasets(clean / "blend_cache.h5")
    assert not partial.exists() and (forged / "field.h5").is_file()


def test_a_lock_left_by_a_killed_run_is_taken_over(world, tmp_path):  # noqa: F811
    """A run killed with SIGKILL leaves its `<out>.lock` (the kernel released the lock): the
    next run takes it over and removes it at the end."""
    (tmp_path / "field.h5.lock").write_text("999999\n")
    assert main(_field(world, tmp_path)) == 0
    assert not (tmp_path / "field.h5.lock").exists() and (tmp_path / "field.h5").is_file()


@pytest.mark.slow
def test_two_concurrent_fits_of_one_output(world, tmp_path):  # noqa: F811
    """Two `goi fit-field` runs of the same --out started together, three times: one valid
    field and one clean refusal each time (the lock naming the other run, or, when the first
    has already finished, the existing output); never a crash, never no field."""
    from stages.semantics.field import load_field

    for rep in range(3):
        d = tmp_path / f"r{rep}"
        d.mkdir()
        argv = [sys.executable, "-m", "goi_cli", *_field(world, d, "--iterations", "10")]
        runs = [subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.PIPE, text=True) for _ in range(2)]  # fmt: skip
        results = [(p.wait(timeout=120), p.stderr.read()) for p in runs]  # type: ignore[union-attr]
        codes = sorted(c for c, _ in results)
        assert codes == [0, 2], results
        err = next(e for c, e in results if c == 2)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("goi: error: --out"), err
        assert "another goi run (pid" in err or "already exists" in err, err
        load_field(d / "field.h5")
        assert sorted(p.name for p in d.iterdir()) == ["blend_cache.h5", "field.h5"]
