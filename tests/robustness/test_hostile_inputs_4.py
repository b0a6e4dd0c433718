"""Hostile inputs, fifth sweep (docs/reliability.md): `goi batch` owning Snakemake, checking
every stage's inputs and its output directory, YAML depth; the RES index read like every
artifact; export-model checking the checkpoint before building the model; the distributed
fit's one-line failures.

Each case goes through the real CLI and must give exit 2, one `goi: error:` line naming the
file, field or option, no traceback, and leave every byte of its inputs and of the place it
writes to as it was (the assertions of test_hostile_inputs.py). Beside the table: one real
batch run from a working directory holding a hostile Snakemake profile, with $SNAKEMAKE_PROFILE
set and shell metacharacters in a path, a prompt and its id (no marker script runs, the
answers land where the batch looks, a rerun does nothing); the RES index's partial file and
`goi inspect`; a SafetensorError while loading.
"""

import json
import os
import shutil
import socket
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest

from goi_cli.main import main
from tests.query.test_res_index import photographed  # noqa: F401  (a scene with photos)
from tests.robustness.test_hostile_inputs import (
    _copy,
    _digest,
    assert_refused,
    world,  # noqa: F401  (the shared fixture)
)

pytest.importorskip("yaml")
pytest.importorskip("snakemake")

ROOT = Path(__file__).resolve().parents[2]
#: What a hostile profile or path would run; no case may ever create it.
MARKER = "goi-marker-ran"


@dataclass
class Case:
    name: str
    make: Callable  # (world, tmp) -> argv; may write broken inputs into tmp
    words: tuple[str, ...]
    subprocess: bool = False  # run in a child: C-level stderr (torch's C++ log) shows there
    env: Callable | None = None  # (world, tmp) -> extra environment of the child


# --- goi batch -----------------------------------------------------------------------------


def _scene_entry(s, **edit) -> dict:
    """One scene of the paper's route on the shared world (its features, embeddings, masks)."""
    w = s["w"]
    entry = {"scene": str(s["scene"]), "features": str(s["features"]),
             "text_embeddings": str(w / "text.json"), "res_masks": str(w / "res"),
             "prompts": ["box"]}  # fmt: skip
    entry.update(edit)
    return {k: v for k, v in entry.items() if v is not None}


def _batch(*args: str, top: dict | None = None, **edit):
    """goi batch of a JSON configuration (JSON is YAML) in the case directory, OUT there too."""

    def make(s, tmp):
        cfg = tmp / "batch.json"
        cfg.write_text(json.dumps({**(top or {}), "scenes": [_scene_entry(s, **edit)]}))
        return ["batch", str(cfg), "--out", str(tmp / "out"), *args]

    return make


def _raw(text: str, *args: str):
    """goi batch of a configuration written as it is (YAML that JSON cannot say)."""

    def make(s, tmp):
        cfg = tmp / "batch.yaml"
        cfg.write_text(text)
        return ["batch", str(cfg), "--out", str(tmp / "out"), *args]

    return make


def _with(setup: Callable[[object, Path], object], make: Callable):
    def run(s, tmp):
        setup(s, tmp)
        return make(s, tmp)

    return run


def _profile(text: str | None, name: str = "prof"):
    """goi batch --profile DIR, DIR/config.yaml holding `text` (no file when None)."""

    def make(s, tmp):
        d = tmp / name
        d.mkdir()
        if text is not None:
            (d / "config.yaml").write_text(text.replace("MARKER", str(tmp / MARKER)))
        return _batch("--profile", str(d))(s, tmp)

    return make


def _marker_script(tmp: Path) -> Path:
    script = tmp / "evil.sh"
    script.write_text(f"#!/bin/sh\ntouch {tmp / MARKER}\n")
    script.chmod(0o755)
    return script


def _braces(where: str):
    """A scene input whose path holds `{x}`: the scene directory, a feature map, the
    embeddings file or a RES mask."""

    def make(s, tmp):
        if where == "scene":
            d = _copy(s["scene"], tmp / "room{x}")
            return _batch(scene=str(d), name="room")(s, tmp)
        if where == "features":
            d = _copy(s["features"], tmp / "features")
            shutil.copy(next(d.glob("*.npy")), d / "{view}.npy")
            return _batch(features=str(d))(s, tmp)
        if where == "text_embeddings":
            f = _copy(s["w"] / "text.json", tmp / "text{x}.json")
            return _batch(text_embeddings=str(f))(s, tmp)
        d = _copy(s["w"] / "res", tmp / "res")
        shutil.copy(next(d.glob("*.png")), d / "{prompt}.png")
        return _batch(res_masks=str(d))(s, tmp)

    return make


def _user_out(s, tmp):
    """OUT holding the user's own artifacts of an earlier manual run of the same scene."""
    scene_out = tmp / "out" / s["scene"].name
    scene_out.mkdir(parents=True)
    shutil.copy(s["w"] / "f.h5", scene_out / "features.h5")
    shutil.copy(s["w"] / "field.h5", scene_out / "field.h5")


def _goi_out(s, tmp) -> Path:
    state = tmp / "out" / ".goi-batch"
    state.mkdir(parents=True)
    return state


def _user_file(tmp: Path) -> Path:
    f = tmp / "notes.txt"
    f.write_text("the user's own file\n")
    return f


def _deep(n: int, block: bool = False) -> str:
    if block:  # indentation, 2 spaces a level
        return "".join(f"{'  ' * i}a:\n" for i in range(n)) + f"{'  ' * n}b: 1\n"
    return "[" * n + "]" * n + "\n"


def _embeddings_with_nan(s, tmp):
    f = tmp / "text.json"
    f.write_text('{"box": [NaN, 1.0]}')
    return _batch(text_embeddings=str(f))(s, tmp)


def _res_index_of_another_kind(s, tmp):
    idx = _copy(s["w"] / "c.h5", tmp / "index.h5")  # a codebook, not an index
    return _batch(res_masks=None, res_index=str(idx), lift=True)(s, tmp)


BATCH = [
    # 1. goi batch owns Snakemake: its own options after --, a named profile, pattern paths
    Case("batch -- --config python=<a script>",
         lambda s, t: _batch("--", "--config", f"python={_marker_script(t)}")(s, t),
         ("--config", "goi batch sets")),
    Case("batch -- -C python=<a script>",
         lambda s, t: _batch("--", "-C", f"python={_marker_script(t)}")(s, t), ("-C", "--config")),
    Case("batch -- --configfile evil.yaml", _batch("--", "--configfile", "evil.yaml"),
         ("--configfile", "plan.json")),
    Case("batch -- --configf evil.yaml (an abbreviation Snakemake accepts)",
         _batch("--", "--configf", "evil.yaml"), ("--configf", "--configfile")),
    Case("batch -- --configfile=evil.yaml", _batch("--", "--configfile=evil.yaml"),
         ("--configfile",)),
    Case("batch -- --directory /tmp", _batch("--", "--directory", "/tmp"), ("--directory",)),
    Case("batch -- -nd /tmp (clustered short options)", _batch("--", "-nd", "/tmp"),
         ("-nd", "--directory")),
    Case("batch -- --snakefile=evil.smk", _batch("--", "--snakefile=evil.smk"),
         ("--snakefile",)),
    Case("batch -- -s evil.smk", _batch("--", "-s", "evil.smk"), ("-s", "--snakefile")),
    Case("batch -- --profile somewhere", _batch("--", "--profile", "somewhere"),
         ("--profile", "goi batch --profile")),
    Case("batch -- --workflow-profile profiles/default",
         _batch("--", "--workflow-profile", "profiles/default"), ("--workflow-profile",)),
    Case("batch -- --nolock", _batch("--", "--nolock"), ("--nolock", "locks OUT")),
    Case("batch -- --unlock", _batch("--", "--unlock"), ("--unlock",)),
    Case("batch --profile whose config.yaml sets config: python=<a script>",
         _profile("config:\n  - python=MARKER\n"), ("config.yaml", "line 2", "--config")),
    Case("batch --profile whose config.yaml sets directory",
         _profile("jobs: 4\ndirectory: /tmp\n"), ("config.yaml", "line 2", "--directory")),
    Case("batch --profile whose config.yaml sets --configfile",
         _profile("--configfile: evil.yaml\n"), ("config.yaml", "--configfile")),
    Case("batch --profile whose config.yaml names another profile",
         _profile("workflow-profile: elsewhere\n"), ("config.yaml", "--workflow-profile")),
    Case("batch --profile a YTE template whose keys become --configfile",
         _profile('__use_yte__: true\n?"config" + "file": plan.json\n'),
         ("config.yaml", "__use_yte__")),
    Case("batch: options.index-res.part (the parts of index_jobs are goi batch's)",
         _batch(options={"index-res": {"part": "1/2"}}),
         ("options.index-res.part'", "set by goi batch")),
    Case("batch --profile a directory without config.yaml", _profile(None),
         ("--profile", "config.yaml")),
    Case("batch --profile that does not exist",
         lambda s, t: _batch("--profile", str(t / "nowhere"))(s, t),
         ("--profile", "no such file")),
    Case("batch --profile whose config.yaml is 5,000 levels deep", _profile(_deep(5000)),
         ("config.yaml", "nested deeper")),
    Case("batch: a scene directory named room{x}", _braces("scene"),
         ("'scenes[0].scene'", "{x}", "wildcard")),
    Case("batch: a feature map named {view}.npy", _braces("features"),
         ("'scenes[0].features'", "{view}")),
    Case("batch: an embeddings file named text{x}.json", _braces("text_embeddings"),
         ("'scenes[0].text_embeddings'", "{x}")),
    Case("batch: a RES mask named {prompt}.png", _braces("res_masks"),
         ("'scenes[0].res_masks'", "{prompt}")),
    # 2. every stage's inputs, checked by the stages' own checks before Snakemake starts
    Case("batch: a prompt with a control character", _batch(prompts=["box\u0007"]),
         ("batch.json", "'scenes[0].prompts[0]'", "control characters")),
    Case("batch: a prompt with only a zero-width space", _batch(prompts=["\u200b"]),
         ("'scenes[0].prompts[0]'", "no visible character")),
    Case("batch: a prompt of 1,001 characters", _batch(prompts=["x" * 1001]),
         ("'scenes[0].prompts[0]'", "1001 characters")),
    Case("batch: a prompt id '../escape'",
         _batch(prompts=[{"text": "box", "id": "../escape"}]),
         ("'scenes[0].prompts[0].id'", "not a plain name")),
    Case("batch: a prompt id 'a/b'", _batch(prompts=[{"text": "box", "id": "a/b"}]),
         ("'scenes[0].prompts[0].id'", "not a plain name")),
    Case("batch: a prompt missing from the embeddings (its fourth job would fail)",
         _batch(prompts=["box", "lamp"]),
         ("'scenes[0].prompts[1]'", "text.json", "no embedding for prompt 'lamp'")),
    Case("batch: the paper's route without embeddings or a bundle",
         _batch(text_embeddings=None), ("scenes[0]", "text embedding")),
    Case("batch: embeddings holding NaN", _embeddings_with_nan, ("text.json", "NaN")),
    Case("batch: a prompt id whose RES masks are not there",
         _batch(prompts=[{"text": "box", "id": "o9"}]),
         ("'scenes[0].prompts[0]'", "--res-masks", "o9")),
    Case("batch: options.fit-field.iterations 'many'",
         _batch(options={"fit-field": {"iterations": "many"}}),
         ("'options.fit-field.iterations'", "many")),
    Case("batch: options.fit-field.iterations -5",
         _batch(options={"fit-field": {"iterations": -5}}), ("'options.fit-field.iterations'",)),
    Case("batch: options.query.export 'everything'",
         _batch(options={"query": {"export": "everything"}}),
         ("'options.query.export'", "everything")),
    Case("batch: options.query.refit 3 (a flag given a value)",
         _batch(options={"query": {"refit": 3}}), ("'options.query.refit'", "true or false")),
    Case("batch: options.fit-field.iterations true (a value given as a flag)",
         _batch(options={"fit-field": {"iterations": True}}),
         ("'options.fit-field.iterations'", "a value")),
    Case("batch: options.init-codebook.seed 1.5",
         _batch(options={"init-codebook": {"seed": 1.5}}), ("'options.init-codebook.seed'",)),
    Case("batch: a RES index without a bundle", _res_index_of_another_kind,
         ("'scenes[0].res_index'", "--bundle")),
    Case("batch: res_index true with a bundle that is not one",
         lambda s, t: _batch(res_masks=None, res_index=True, lift=True,
                             bundle=str((t / "b").mkdir() or t / "b"))(s, t),
         ("'scenes[0].res_index'", "cannot be built", "manifest.json")),  # fmt: skip
    # 3. OUT is goi batch's own
    Case("batch --out holding the user's features.h5 and field.h5 of the scene",
         _with(_user_out, _batch()), ("--out", "did not make", "--force")),
    Case("batch --out a file",
         lambda s, t: [a if a != str(t / "out") else str(_user_file(t)) for a in _batch()(s, t)],
         ("--out", "is a file")),
    Case("batch --out whose .goi-batch is a symlink to the user's directory",
         _with(lambda s, t: ((t / "out").mkdir(), (t / "mine").mkdir(),
                             (t / "out" / ".goi-batch").symlink_to(t / "mine")), _batch()),
         ("--out", ".goi-batch")),  # fmt: skip
    Case("batch --out whose plan.json is a directory",
         _with(lambda s, t: (_goi_out(s, t) / "plan.json").mkdir(), _batch()),
         ("plan.json", "directory")),
    Case("batch --out whose run.lock is a symlink to the user's file",
         _with(lambda s, t: (_goi_out(s, t) / "run.lock").symlink_to(_user_file(t)), _batch()),
         ("--out", "lock")),
    # 4. YAML depth, before PyYAML composes
    Case("batch: a configuration 5,000 lists deep", _raw(_deep(5000)), ("line 1", "nested deeper")),
    Case("batch: a configuration 5,000 mappings deep (flow)",
         _raw("{a: " * 5000 + "1" + "}" * 5000 + "\n"), ("nested deeper",)),
    Case("batch: a configuration 40 mappings deep (block)", _raw(_deep(40, block=True)),
         ("line 33", "nested deeper")),
    Case("batch: YAML aliases that expand to a billion values",
         _raw("a: &a [x, x, x, x, x, x, x, x, x, x]\n"
              + "".join(f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
                        for p, c in zip("abcdefgh", "bcdefghi", strict=True))),
         ("more than 200000 values",)),  # fmt: skip
]  # fmt: skip


# --- export-model --------------------------------------------------------------------------


def _safetensors(header: dict, body: int = 16) -> bytes:
    raw = json.dumps(header).encode()
    return len(raw).to_bytes(8, "little") + raw + b"\0" * body


def _checkpoint(config: dict, *, pre: dict | None = None, weights: bytes | None = None):
    """export-model of one checkpoint directory: `config` as config.json, a tokenizer, an
    optional preprocessor_config.json, weights whose header is sound unless given."""

    def make(s, tmp):
        ck = tmp / "ckpt"
        ck.mkdir()
        (ck / "config.json").write_text(json.dumps(config))
        (ck / "tokenizer.json").write_text("{}")
        if pre is not None:
            (ck / "preprocessor_config.json").write_text(json.dumps(pre))
        (ck / "model.safetensors").write_bytes(weights or _safetensors({}))
        return ["export-model", str(ck), "--out", str(tmp / "bundle")]

    return make


def _tensors(*ranges: tuple[int, int], meta: object = None) -> bytes:
    header: dict = {f"t{i}": {"dtype": "F32", "shape": [(b - a) // 4], "data_offsets": [a, b]}
                    for i, (a, b) in enumerate(ranges)}  # fmt: skip
    if meta is not None:
        header["__metadata__"] = meta
    return _safetensors(header, max(b for _, b in ranges))


SAM = {"model_type": "sam", "vision_config": {"model_type": "sam_vision_model"},
       "prompt_encoder_config": {}, "mask_decoder_config": {}}  # fmt: skip
CLIP = {"model_type": "clip", "text_config": {}, "vision_config": {}}


def _sub(base: dict, section: str, **values) -> dict:
    out = json.loads(json.dumps(base))
    out[section] = {**out.get(section, {}), **values}
    return out


EXPORT = [
    Case("export-model: SAM whose vision_config declares 100,000 layers (built for ever)",
         _checkpoint(_sub(SAM, "vision_config", num_hidden_layers=100_000)),
         ("config.json", "'vision_config.num_hidden_layers'", "100000")),
    Case("export-model: CLIP text_config.hidden_size 10**9",
         _checkpoint(_sub(CLIP, "text_config", hidden_size=10**9)),
         ("'text_config.hidden_size'",)),
    Case("export-model: CLIP vision_config.image_size 10**6",
         _checkpoint(_sub(CLIP, "vision_config", image_size=10**6)),
         ("'vision_config.image_size'",)),
    Case("export-model: CLIP vision_config.num_attention_heads 0",
         _checkpoint(_sub(CLIP, "vision_config", num_attention_heads=0)),
         ("'vision_config.num_attention_heads'",)),
    Case("export-model: CLIP text_config.num_hidden_layers '12' (text)",
         _checkpoint(_sub(CLIP, "text_config", num_hidden_layers="12")),
         ("'text_config.num_hidden_layers'", "integer")),
    Case("export-model: CLIP text_config.vocab_size true",
         _checkpoint(_sub(CLIP, "text_config", vocab_size=True)), ("'text_config.vocab_size'",)),
    Case("export-model: Grounding DINO backbone depths [2, 2, 10**6, 2]",
         _checkpoint({"model_type": "grounding-dino",
                      "backbone_config": {"model_type": "swin", "depths": [2, 2, 10**6, 2]}}),
         ("'backbone_config.depths'",)),
    Case("export-model: Grounding DINO num_queries 10**9",
         _checkpoint({"model_type": "grounding-dino", "num_queries": 10**9}), ("'num_queries'",)),
    Case("export-model: model_type sam on a CLIP config (text_config)",
         _checkpoint({**CLIP, "model_type": "sam"}), ("config.json", "'text_config'", "sam")),
    Case("export-model: model_type clip whose vision_config is SAM's",
         _checkpoint(_sub(CLIP, "vision_config", model_type="sam_vision_model")),
         ("'vision_config.model_type'", "sam_vision_model")),
    Case("export-model: SAM whose vision_config is a list",
         _checkpoint({**SAM, "vision_config": [1, 2]}), ("'vision_config'", "mapping")),
    Case("export-model: preprocessor image_mean 'abc'",
         _checkpoint(CLIP, pre={"image_mean": "abc"}),
         ("preprocessor_config.json", "'image_mean'")),
    Case("export-model: preprocessor image_std [0, 0, 0]",
         _checkpoint(CLIP, pre={"image_std": [0, 0, 0]}),
         ("preprocessor_config.json", "'image_std'")),
    Case("export-model: preprocessor image_mean [true, 0.5, 0.5]",
         _checkpoint(CLIP, pre={"image_mean": [True, 0.5, 0.5]}), ("'image_mean'",)),
    Case("export-model: preprocessor size 'big'", _checkpoint(CLIP, pre={"size": "big"}),
         ("preprocessor_config.json", "'size'")),
    Case("export-model: preprocessor size {height: 10**7}",
         _checkpoint(CLIP, pre={"size": {"height": 10**7, "width": 224}}), ("'size'",)),
    Case("export-model: safetensors tensors aliasing the same bytes",
         _checkpoint(CLIP, weights=_tensors((0, 16), (0, 16))),
         ("model.safetensors", "share bytes")),
    Case("export-model: safetensors tensors overlapping",
         _checkpoint(CLIP, weights=_tensors((0, 16), (8, 24))),
         ("model.safetensors", "share bytes")),
    Case("export-model: safetensors with a hole between tensors",
         _checkpoint(CLIP, weights=_tensors((0, 16), (20, 24))), ("model.safetensors", "'t1'")),
    Case("export-model: safetensors __metadata__ {format: 1}",
         _checkpoint(CLIP, weights=_tensors((0, 16), meta={"format": 1})),
         ("model.safetensors", "__metadata__")),
]  # fmt: skip


# --- the distributed fit -------------------------------------------------------------------


class _Service:
    """A TCP service on a free port that is not a torch rendezvous: it answers HTTP-like
    bytes and closes, or accepts and never answers."""

    def __init__(self, answer: bool):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port = self.sock.getsockname()[1]
        self.answer = answer
        self.held: list[socket.socket] = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:
                return
            if self.answer:
                c.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
                c.close()
            else:
                self.held.append(c)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank(port: Callable[[], int]):
    """Rank 1 of 2 joining MASTER_PORT `port()`, with a 2 s timeout."""

    def env(s, tmp):
        return {"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "LOCAL_WORLD_SIZE": "1",
                "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port())}  # fmt: skip

    return env


def _dist(s, tmp):
    w = s["w"]
    return ["fit-field", "--distributed", "--scene", str(s["scene"]), "--features",
            str(w / "f.h5"), "--codebook", str(w / "c.h5"), "--dist-timeout-s", "2",
            "--out", str(tmp / "field.h5")]  # fmt: skip


DIST = [
    Case("fit-field --distributed: a rank with no rank 0", _dist,
         ("--distributed", "the rendezvous failed"), subprocess=True, env=_rank(_free_port)),
    Case("fit-field --distributed: MASTER_PORT answered by another service", _dist,
         ("--distributed", "the rendezvous failed"), subprocess=True,
         env=_rank(lambda: _Service(answer=True).port)),
    Case("fit-field --distributed: MASTER_PORT of a service that never answers (hung before)",
         _dist, ("--distributed", "never answered as a torch rendezvous"), subprocess=True,
         env=_rank(lambda: _Service(answer=False).port)),
]  # fmt: skip


# --- running a case ------------------------------------------------------------------------


def _run(case: Case, argv: list[str], world, tmp: Path, capsys) -> tuple[int, str]:  # noqa: F811
    if not case.subprocess:
        capsys.readouterr()
        code = main(argv)
        return code, capsys.readouterr().err
    env = {**os.environ, **(case.env(world, tmp) if case.env else {})}
    done = subprocess.run([sys.executable, "-m", "goi_cli", *argv], capture_output=True,
                          text=True, timeout=180, cwd=ROOT, env=env)  # fmt: skip
    return done.returncode, done.stderr


def _refused(case: Case, world, tmp: Path, capsys, watched: list[Path]) -> None:  # noqa: F811
    argv = case.make(world, tmp)
    before = {str(d): _digest(d) for d in [tmp, *watched]}
    code, err = _run(case, argv, world, tmp, capsys)
    assert_refused(code, err, case.words)
    for d in [tmp, *watched]:
        assert _digest(d) == before[str(d)], f"{d} changed"
    assert not list(tmp.rglob(MARKER)), "a hostile script ran"


FAST = BATCH + EXPORT


@pytest.mark.parametrize("case", FAST, ids=[c.name for c in FAST])
def test_hostile_input(case, world, tmp_path, capsys):  # noqa: F811
    if case in EXPORT:
        pytest.importorskip("transformers")
    _refused(case, world, tmp_path, capsys, [world["w"], world["scene"], world["features"]])


@pytest.mark.slow
@pytest.mark.parametrize("case", DIST, ids=[c.name for c in DIST])
def test_hostile_distributed_rendezvous(case, world, tmp_path, capsys):  # noqa: F811
    _refused(case, world, tmp_path, capsys, [world["w"], world["scene"]])


# --- the RES index -------------------------------------------------------------------------

PROMPT = "the red box"


@pytest.fixture(scope="module")
def indexed(photographed, res_bundles):  # noqa: F811
    """A scene with its photos (goi's renderings), the tiny Grounded-SAM bundle, and the
    scene's RES index built once."""
    s, root = photographed
    bundle = res_bundles["grounded"]
    idx = root / "index-hostile.h5"
    assert main(["index-res", "--scene", str(s["scene"]), "--bundle", str(bundle),
                 "--out", str(idx)]) == 0  # fmt: skip
    return {"scene": s["scene"], "bundle": bundle, "index": idx, "train": s["train"]}


def _first(f: h5py.File) -> tuple[str, h5py.Group]:
    name = next(iter(f["views"]))
    return name, f["views"][name]


def _float_key(g: h5py.Group) -> str:
    return next(k for k in g if g[k].dtype.kind == "f")


def _edit(edit: Callable[[h5py.File, Path], None]):
    """query --lift from a copy of the index that `edit(file, case dir)` changed."""

    def make(x, tmp):
        idx = _copy(x["index"], tmp / "index.h5")
        with h5py.File(idx, "r+") as f:
            edit(f, tmp)
        return ["query", "--scene", str(x["scene"]), "--prompt", PROMPT, "--lift",
                "--res-index", str(idx), "--bundle", str(x["bundle"]),
                "--out", str(tmp / "q")]  # fmt: skip

    return make


def _set_value(value: float):
    def edit(f, tmp):
        _, g = _first(f)
        k = _float_key(g)
        a = g[k][()]
        a.flat[a.size // 2] = value
        g[k][...] = a

    return edit


def _view_as_dataset(f, tmp):
    name, g = _first(f)
    attrs = dict(g.attrs)
    del f["views"][name]
    ds = f["views"].create_dataset(name, data=np.zeros(4, np.float32))
    ds.attrs.update(attrs)  # what the schema asks of a view, on a dataset


def _views_as_dataset(f, tmp):
    del f["views"]
    f.create_dataset("views", data=np.zeros(4, np.float32))


def _external_view(f, tmp):
    name, _ = _first(f)
    other = tmp / "other.h5"
    shutil.copy(f.filename, other)
    del f["views"][name]
    f["views"][name] = h5py.ExternalLink(str(other), f"/views/{name}")


def _soft_view(f, tmp):
    names = list(f["views"])
    del f["views"][names[1]]
    f["views"][names[1]] = h5py.SoftLink(f"/views/{names[0]}")  # one view's arrays as two


def _external_storage(f, tmp):
    _, g = _first(f)
    k = _float_key(g)
    a = g[k][()]
    raw = tmp / "raw.bin"
    a.tofile(raw)
    del g[k]
    g.create_dataset(k, shape=a.shape, dtype=a.dtype, external=[(str(raw), 0, a.nbytes)])


def _virtual(f, tmp):
    _, g = _first(f)
    k = _float_key(g)
    a = g[k][()]
    src = tmp / "src.h5"
    with h5py.File(src, "w") as o:
        o["a"] = a
    layout = h5py.VirtualLayout(shape=a.shape, dtype=a.dtype)
    layout[...] = h5py.VirtualSource(str(src), "a", shape=a.shape)
    del g[k]
    g.create_virtual_dataset(k, layout)


def _respec(change: Callable[[list, str], tuple[list, str]]):
    """The spec and every view's array of one key changed alike (a consistent file of other
    arrays than the bundle's)."""

    def edit(f, tmp):
        spec = json.loads(str(f.attrs["arrays"]))
        _, g0 = _first(f)
        k = _float_key(g0)
        shape, dtype = change(*spec[k])
        spec[k] = [shape, dtype]
        f.attrs["arrays"] = json.dumps(spec)
        for name in f["views"]:
            g = f["views"][name]
            del g[k]
            g.create_dataset(k, data=np.zeros(shape, dtype))

    return edit


def _spec_attr(value: str):
    def edit(f, tmp):
        f.attrs["arrays"] = value

    return edit


def _view_attr(key: str, value):
    def edit(f, tmp):
        _first(f)[1].attrs[key] = value

    return edit


def _huge_spec(f, tmp):
    spec = json.loads(str(f.attrs["arrays"]))
    k = next(iter(spec))
    spec[k] = [[10**6, 10**6], spec[k][1]]
    f.attrs["arrays"] = json.dumps(spec)


def _batch_with_index(edit: Callable[[h5py.File, Path], None]):
    """goi batch of a field-free scene whose given RES index `edit` damaged: refused by the
    query's own index check before Snakemake starts."""

    def make(x, tmp):
        idx = _copy(x["index"], tmp / "index.h5")
        with h5py.File(idx, "r+") as f:
            edit(f, tmp)
        cfg = tmp / "batch.json"
        scene = {"scene": str(x["scene"]), "bundle": str(x["bundle"]), "res_index": str(idx),
                 "lift": True, "prompts": [PROMPT]}  # fmt: skip
        cfg.write_text(json.dumps({"scenes": [scene]}))
        return ["batch", str(cfg), "--out", str(tmp / "out")]

    return make


INDEX = [
    Case("RES index: a NaN in a view's array", _edit(_set_value(np.nan)),
         ("index.h5", "NaN or infinite")),
    Case("RES index: an infinity in a view's array", _edit(_set_value(np.inf)),
         ("index.h5", "NaN or infinite")),
    Case("RES index: a dataset where a view's group belongs", _edit(_view_as_dataset),
         ("index.h5", "should be a group")),
    Case("RES index: a dataset where 'views' belongs", _edit(_views_as_dataset),
         ("index.h5", "'views' should be a group")),
    Case("RES index: a view that is an external link to another file", _edit(_external_view),
         ("index.h5", "ExternalLink", "other.h5")),
    Case("RES index: a view that is a soft link to another view", _edit(_soft_view),
         ("index.h5", "SoftLink")),
    Case("RES index: an array stored in another file (external storage)",
         _edit(_external_storage), ("index.h5", "another file")),
    Case("RES index: an array that is a virtual dataset of another file", _edit(_virtual),
         ("index.h5", "another file")),
    Case("RES index: arrays of another shape than the bundle's image side",
         _edit(_respec(lambda shape, dtype: ([*shape[:-1], shape[-1] + 1], dtype))),
         ("index.h5", "the bundle's image side")),
    Case("RES index: arrays of another dtype than the bundle's image side",
         _edit(_respec(lambda shape, dtype: (shape, "float64" if dtype != "float64"
                                             else "float32"))),
         ("index.h5", "the bundle's image side")),  # fmt: skip
    Case("RES index: 'arrays' declaring 10**12 elements", _edit(_huge_spec),
         ("index.h5", "'arrays'", "MiB")),
    Case("RES index: 'arrays' that is not JSON", _edit(_spec_attr("{nope")),
         ("index.h5", "'arrays'")),
    Case("RES index: a view indexed at another size than its camera",
         _edit(_view_attr("width", 4096)), ("index.h5", "4096x", "another scene")),
    Case("RES index: a view's width as text", _edit(_view_attr("width", "wide")),
         ("index.h5", "'width'")),
    Case("batch: a given RES index holding a NaN", _batch_with_index(_set_value(np.nan)),
         ("batch.json", "'scenes[0].res_index'", "NaN or infinite")),
    Case("batch: a given RES index with a view as an external link",
         _batch_with_index(_external_view), ("'scenes[0].res_index'", "ExternalLink")),
]  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("case", INDEX, ids=[c.name for c in INDEX])
def test_hostile_res_index(case, indexed, tmp_path, capsys):
    _refused(case, indexed, tmp_path, capsys, [indexed["scene"], indexed["bundle"]])


def test_enough_cases():
    assert len(BATCH) + len(EXPORT) + len(INDEX) + len(DIST) >= 45


# --- outcomes that are not refusals --------------------------------------------------------


def test_a_block_scalar_prompt_is_named_as_goi_query_names_it(world, tmp_path):  # noqa: F811
    """`text: |` ends the prompt with a newline; goi query strips it before naming the answer's
    directory, so the batch does too (it looked for the answer elsewhere before)."""
    from stages.batch.config import load_batch
    from stages.query.prompts import safe_name

    w = world["w"]
    cfg = tmp_path / "b.yaml"
    cfg.write_text(
        f"scenes:\n  - scene: {world['scene']}\n    features: {world['features']}\n"
        f"    text_embeddings: {w / 'text.json'}\n    res_masks: {w / 'res'}\n"
        "    prompts:\n      - text: |\n          box\n"
    )
    (p,) = load_batch(cfg).scenes[0].prompts
    assert (p.prompt.text, p.prompt.name) == ("box", safe_name("box"))


def test_a_safetensors_error_while_loading_is_one_line(tmp_path, monkeypatch):
    """Whatever safetensors refuses that goi's header check lets through is one GoiError
    naming the checkpoint, never an internal error."""
    pytest.importorskip("transformers")
    from safetensors import SafetensorError

    from stages.core.errors import GoiError
    from stages.models.export.common import load_model

    class Model:
        @staticmethod
        def from_pretrained(*a, **k):
            raise SafetensorError("Error while deserializing header: invalid offset")

    with pytest.raises(GoiError, match=r"cannot load it as a SAM checkpoint \(Error while"):
        load_model(Model, tmp_path, "SAM", {})


@pytest.mark.slow
def test_a_resumed_partial_index_keeps_only_sound_views(indexed, tmp_path, capsys):
    """A `.partial` of the same inputs whose finished view holds a NaN is not resumed: the
    index is built again, and the result is the clean build's."""
    from stages.query.res_index import load_res_index

    out = tmp_path / "index.h5"
    partial = _copy(indexed["index"], tmp_path / "index.h5.partial")
    with h5py.File(partial, "r+") as f:
        _set_value(np.nan)(f, tmp_path)
    capsys.readouterr()
    argv = ["index-res", "--scene", str(indexed["scene"]), "--bundle", str(indexed["bundle"]),
            "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "NaN or infinite" in err and "building the index again" in err, err
    assert not partial.exists()
    clean, built = load_res_index(indexed["index"]), load_res_index(out)
    for v in clean.views:
        a, b = clean.image_side(v), built.image_side(v)
        assert all(np.array_equal(a[k], b[k]) for k in a)


@pytest.mark.slow
def test_goi_inspect_calls_a_damaged_index_invalid(indexed, tmp_path, capsys):
    """goi inspect runs the index's reader: a dataset in place of a view, a NaN and an
    external link are each a problem it names (it called the first one valid before)."""
    for edit, words in ((_view_as_dataset, "should be a group"),
                        (_set_value(np.nan), "NaN or infinite"),
                        (_external_view, "ExternalLink")):  # fmt: skip
        d = tmp_path / edit.__name__
        d.mkdir()
        idx = _copy(indexed["index"], d / "index.h5")
        with h5py.File(idx, "r+") as f:
            edit(f, d)
        capsys.readouterr()
        assert main(["inspect", str(idx)]) == 2
        out = capsys.readouterr().out
        assert words in out and "0 errors" not in out, out
    assert main(["inspect", str(indexed["index"])]) == 0


@pytest.mark.slow
def test_batch_from_a_hostile_checkout(world, tmp_path, monkeypatch, capsys):  # noqa: F811
    """A real batch (the field-free route, one prompt) started from a directory holding a
    workflow profile that makes a marker script the jobs' interpreter, with $SNAKEMAKE_PROFILE
    naming another such profile, a scene path, a prompt and a prompt id full of shell syntax,
    and OUT/.goi-batch/plan.json.tmp a symlink to the user's file: no marker script runs, no
    shell command runs, the user's file is untouched, the answer lands where the batch looks;
    the same batch again does nothing."""
    from stages.query.prompts import safe_name
    from stages.query.selection import load_selection

    script = _marker_script(tmp_path)
    cwd = tmp_path / "checkout"
    (cwd / "profiles" / "default").mkdir(parents=True)
    (cwd / "profiles" / "default" / "config.yaml").write_text(f"config:\n  - python={script}\n")
    env_profile = tmp_path / "envprofile"
    env_profile.mkdir()
    (env_profile / "config.yaml").write_text(f"config:\n  - python={script}\n")
    monkeypatch.chdir(cwd)
    monkeypatch.setenv("SNAKEMAKE_PROFILE", str(env_profile))
    # relative: a job runs in OUT, inside tmp_path (and a path component holds no '/')
    shell = f"$(touch {MARKER}) `touch {MARKER}`; touch {MARKER}"
    scene = _copy(world["scene"], tmp_path / f"scan '\"{shell}" / "scene")
    pid = f"id $(touch {MARKER})`touch {MARKER}`"
    res = _copy(world["w"] / "res", tmp_path / "res" / pid)
    prompt = f"the box \"{shell}' {{braces}} $HOME"
    cfg = tmp_path / "batch.json"
    cfg.write_text(json.dumps({"scenes": [{
        "scene": str(scene), "name": "room", "res_masks": str(res.parent), "lift": True,
        "options": {"query": {"export": "none", "steps": 100}},
        "prompts": [{"text": prompt, "id": pid}]}]}))  # fmt: skip
    out = tmp_path / "out"
    (out / ".goi-batch").mkdir(parents=True)
    mine = _user_file(tmp_path)
    (out / ".goi-batch" / "plan.json.tmp").symlink_to(mine)
    capsys.readouterr()
    assert main(["batch", str(cfg), "--out", str(out)]) == 0, capsys.readouterr().err[-3000:]
    assert "new, 1/1" in capsys.readouterr().out
    key = safe_name(prompt)
    sel = load_selection(out / "room" / "prompts" / key / key / "selection.h5")
    assert sel.prompt == prompt and sel.mode == "lifted"
    assert not list(tmp_path.rglob(MARKER))
    assert mine.read_text() == "the user's own file\n"
    assert json.loads((out / ".goi-batch" / "plan.json").read_text())["python"] == sys.executable
    # nothing is out of date: nothing runs
    assert main(["batch", str(cfg), "--out", str(out)]) == 0
    assert "0 new, 1/1" in capsys.readouterr().out
    assert not list(tmp_path.rglob(MARKER))
