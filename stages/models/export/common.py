"""What every export shares: reading a checkpoint, the ONNX export call, and the check of each
ONNX file against torch before a bundle is written.

The check runs the ONNX file once in onnxruntime on the inputs the torch outputs were computed
from. Most graphs must agree within max(1e-3, 1e-4 x the largest output value). The detector is
checked on what goi uses of it (`check_detections`): at the real size its raw logits differ from
torch's by up to ~1e-2 from float32 summation order alone, as torch differs from itself with
another thread count (docs/models.md).
"""

from __future__ import annotations

import os
import shutil
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from stages.core.errors import GoiError, warn
from stages.core.files import read_json, regular_file
from stages.core.torch_numerics import settle_vml
from stages.models.onnx_io import Tokens

TOLERANCE = 1e-4
#: The absolute floor of the check (what goi's CLIP export always allowed).
FLOOR = 1e-3


def transformers() -> Any:
    try:
        import transformers as tf

        tf.utils.logging.disable_progress_bar()
        tf.utils.logging.set_verbosity_error()
    except ImportError:
        raise GoiError(
            "goi export-model needs transformers, the optional extra goi[export]: "
            "pip install 'goi[export]' (bash scripts/goi.sh export-model ... installs it)"
        ) from None
    return tf


def checkpoint_json(path: Path) -> Any:
    return read_json(path, "missing (a Hugging Face checkpoint directory needs it)")


def check_weights(src: Path, cfg: dict) -> dict[str, tuple[Path, str]]:
    """The checkpoint's tensors (name -> file, dtype), from the safetensors files transformers
    will read, each header checked before transformers opens a file. It reads config.json's
    `transformers_weights` when it names a file, else `model.safetensors`, else the shards
    that `model.safetensors.index.json` names. Only safetensors are ever read: goi never hands
    a pickle (a .bin) to torch."""
    single, index = src / "model.safetensors", src / "model.safetensors.index.json"
    named = cfg.get("transformers_weights")
    if named is not None:
        ok = isinstance(named, str) and named.endswith((".safetensors", ".safetensors.index.json"))
        if not (ok and _own_file(named)):
            raise GoiError(
                f"{src / 'config.json'}: 'transformers_weights' is {str(named)[:80]!r}; goi "
                "reads a .safetensors file (or its .safetensors.index.json) of the checkpoint "
                "directory only"
            )
        files = _shards(src / named) if named.endswith(".json") else [named]
    elif single.exists() or single.is_symlink():
        files = [single.name]
    elif index.exists() or index.is_symlink():
        files = _shards(index)
    else:
        bins = (
            "; it has pytorch_model.bin, which goi does not load"
            if (src / "pytorch_model.bin").is_file()
            else ""
        )
        raise GoiError(f"{src}: no model.safetensors{bins} (goi reads safetensors weights only)")
    tensors: dict[str, tuple[Path, str]] = {}
    for name in files:
        for tensor, dtype in check_safetensors(src / name).items():
            if tensor in tensors:  # which one transformers keeps depends on the order it reads
                raise GoiError(
                    f"{src / name}: tensor {tensor[:80]!r} is in {tensors[tensor][0].name} too"
                )
            tensors[tensor] = (src / name, dtype)
    return tensors


def _own_file(name: str) -> bool:
    return Path(name).name == name and not name.startswith(".")


def _shards(index: Path) -> list[str]:
    doc = read_json(index)
    weights = doc.get("weight_map") if isinstance(doc, dict) else None
    if not isinstance(weights, dict) or not weights:
        raise GoiError(f"{index}: needs a non-empty 'weight_map' of tensor names to shard files")
    shards = sorted({str(v) for v in weights.values()})
    for name in shards:
        if not name.endswith(".safetensors"):
            raise GoiError(
                f"{index}: names the shard {name[:80]!r}, which is not a .safetensors file; "
                "goi reads safetensors weights only (never a pickled .bin)"
            )
        if not _own_file(name):
            raise GoiError(f"{index}: the shard {name[:80]!r} is not a file of this directory")
    return shards


#: Bytes per element of the safetensors dtypes.
_DTYPE_BYTES = {
    "BOOL": 1, "U8": 1, "I8": 1, "F8_E4M3": 1, "F8_E5M2": 1, "I16": 2, "U16": 2, "F16": 2,
    "BF16": 2, "I32": 4, "U32": 4, "F32": 4, "I64": 8, "U64": 8, "F64": 8,
}  # fmt: skip


#: The floating-point safetensors dtypes (the others are integers and booleans).
_FLOATS = {"F8_E4M3", "F8_E5M2", "F16", "BF16", "F32", "F64"}


def check_safetensors(path: Path) -> dict[str, str]:
    """A safetensors file whose header is sound: an 8-byte length, that many bytes of a JSON
    object, and each tensor's dtype, shape and byte range inside the file and consistent (its
    bytes are exactly shape x dtype's). Returns each tensor's dtype."""
    import json

    p = regular_file(path, "safetensors weights file")
    size = p.stat().st_size
    try:
        with open(p, "rb") as f:
            head = f.read(8)
            n = int.from_bytes(head, "little") if len(head) == 8 else -1
            if not 2 <= n <= min(size - 8, 100 << 20):
                raise GoiError(f"{p}: not a safetensors file (its header length is broken)")
            header = json.loads(f.read(n).decode("utf-8"))
    except OSError as e:
        raise GoiError(f"{p}: cannot read the weights ({e.strerror or e})") from None
    except (UnicodeDecodeError, ValueError):
        raise GoiError(f"{p}: not a safetensors file (its header is not JSON)") from None
    if not isinstance(header, dict):
        raise GoiError(f"{p}: not a safetensors file (its header is not a JSON object)")
    meta = header.get("__metadata__", {})
    if not isinstance(meta, dict) or not all(isinstance(v, str) for v in meta.values()):
        raise GoiError(f"{p}: its header's __metadata__ is not a mapping of texts")
    data = size - 8 - n
    ranges: list[tuple[int, int, str]] = []
    dtypes: dict[str, str] = {}
    for name, t in header.items():
        if name == "__metadata__":
            continue
        why = _entry_fault(t, data)
        if why:
            raise GoiError(f"{p}: tensor {str(name)[:80]!r} has a broken header entry ({why})")
        ranges.append((t["data_offsets"][0], t["data_offsets"][1], str(name)))
        dtypes[str(name)] = t["dtype"]
    # Each tensor owns its bytes: two tensors over the same bytes (aliased or overlapping)
    # would be two names for one memory, and safetensors refuses them only when loading.
    ranges.sort()
    for (_, end, first), (start, _, second) in zip(ranges, ranges[1:], strict=False):
        if start < end:
            raise GoiError(
                f"{p}: tensors {first[:60]!r} and {second[:60]!r} share bytes (overlapping or "
                "aliased ranges in the header)"
            )
        if start != end:
            raise GoiError(f"{p}: tensor {second[:80]!r} does not start where the one before ends")
    if ranges and (ranges[0][0] != 0 or ranges[-1][1] != data):
        raise GoiError(f"{p}: its tensors do not fill the data that follows the header")
    return dtypes


def _entry_fault(t: object, data: int) -> str:
    """What is wrong with one tensor's header entry, given the bytes of data after the header
    ('' when nothing is)."""
    if not isinstance(t, dict) or t.get("dtype") not in _DTYPE_BYTES:
        dtype = t.get("dtype") if isinstance(t, dict) else None
        return f"dtype {str(dtype)[:20]!r} is not a safetensors dtype"
    shape, offsets = t.get("shape"), t.get("data_offsets")
    if not (isinstance(shape, list) and all(map(_count, shape))):
        return "its shape is not a list of sizes"
    if not (isinstance(offsets, list) and len(offsets) == 2 and all(map(_count, offsets))):
        return "its data_offsets are not two byte offsets"
    a, b = offsets
    if not a <= b <= data:
        return f"its bytes [{a}, {b}) are not inside the {data} bytes of data"
    need = (int(np.prod(shape, dtype=object)) if shape else 1) * _DTYPE_BYTES[t["dtype"]]
    if b - a != need:
        return f"{t['dtype']} {shape} is {need} bytes, but its data_offsets hold {b - a}"
    return ""


def _count(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def load_model(
    cls: Any,
    src: Path,
    what: str,
    tensors: dict[str, tuple[Path, str]],
    unused: tuple[str, ...] = (),
) -> Any:
    """A transformers model from a local safetensors checkpoint whose `tensors` (name -> file,
    dtype: check_weights) are checked, frozen, in eval mode.

    Every weight the model reads must come from the checkpoint as its header says
    (check_loaded); `unused` are the prefixes of weights the export never runs, which may be
    absent."""
    from safetensors import SafetensorError

    try:
        model, info = cls.from_pretrained(
            str(src),
            attn_implementation="eager",
            use_safetensors=True,
            output_loading_info=True,
            ignore_mismatched_sizes=True,  # a mismatch is refused below, naming the tensor
        )
    except (OSError, ValueError, RuntimeError, KeyError, TypeError, SafetensorError) as e:
        first = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
        raise GoiError(f"{src}: cannot load it as a {what} checkpoint ({first})") from None
    check_loaded(model.state_dict(), info, src, what, tensors, unused)
    model.eval()
    model.requires_grad_(False)  # the ONNX tracer refuses trainable tensors as constants
    return model


def check_loaded(
    state: dict[str, Any],
    info: dict,
    src: Path,
    what: str,
    tensors: dict[str, tuple[Path, str]],
    unused: tuple[str, ...] = (),
) -> None:
    """The loaded model's `state` [name -> tensor] against transformers' loading `info` and
    the checkpoint's `tensors` (name -> file, dtype). Refused: a weight the checkpoint lacks
    (transformers draws it at random: the bundle would answer noise; tied weights and
    non-persistent buffers are not in `info`'s missing keys), a tensor of another shape, and
    a tensor whose dtype is not of the kind (floating point or integer) of the model's tensors
    of that name (transformers casts the bytes as the header reads them: an F32 matrix labelled
    I32 becomes weights near 1e9). The kinds are matched by the last part of the name, since
    transformers may rename the rest (Grounding DINO's backbone, SAM 2.1's video layout)."""
    mismatched = sorted(info.get("mismatched_keys", []))
    if mismatched:
        name, got, want = mismatched[0]
        more = f" (and {len(mismatched) - 1} more)" if len(mismatched) > 1 else ""
        raise GoiError(
            f"{src}: tensor {name!r} is {list(got)} in the checkpoint, but the {what} model "
            f"reads {list(want)}{more}"
        )
    missing = sorted(k for k in info.get("missing_keys", []) if not k.startswith(unused))
    if missing:
        first = ", ".join(missing[:3]) + (", ..." if len(missing) > 3 else "")
        why = (
            "is it another architecture's checkpoint?"
            if len(missing) * 2 > len(state)
            else "transformers would initialise them at random"
        )
        raise GoiError(
            f"{src}: {len(missing)} of the {len(state)} weights the {what} model reads are "
            f"missing from the checkpoint ({first}); {why}"
        )
    kinds: dict[str, set[bool]] = {}
    for key, value in state.items():
        kinds.setdefault(key.rsplit(".", 1)[-1], set()).add(bool(value.is_floating_point()))
    for name, (file, dtype) in sorted(tensors.items()):
        kind = kinds.get(name.rsplit(".", 1)[-1], set())
        if len(kind) == 1 and kind != {dtype in _FLOATS}:
            want = "floating point" if True in kind else "integers"
            raise GoiError(
                f"{file}: tensor {name[:80]!r} is {dtype} in its header, but the {what} model "
                f"reads {want} there (transformers would convert the bytes as {dtype} values)"
            )


def preprocessor(src: Path) -> dict:
    """preprocessor_config.json ({} when there is none), its values that goi reads checked:
    image_mean and image_std 3 finite numbers each (std > 0), size a side in pixels or a
    mapping of sides."""
    pre = src / "preprocessor_config.json"
    if not (pre.exists() or pre.is_symlink()):
        return {}
    cfg = checkpoint_json(pre)
    if not isinstance(cfg, dict):
        raise GoiError(f"{pre}: expected a JSON object")
    for key, low in (("image_mean", -1e3), ("image_std", 1e-6)):
        v = cfg.get(key)
        if v is not None and not (
            isinstance(v, list) and len(v) == 3 and all(_number(x, low, 1e3) for x in v)
        ):
            raise GoiError(f"{pre}: '{key}' should be 3 numbers in [{low:g}, 1000], found {v!r}")
    size = cfg.get("size")
    sides = [v for v in size.values() if v is not None] if isinstance(size, dict) else [size]
    if size is not None and not all(_number(x, 1, 4096) and isinstance(x, int) for x in sides):
        raise GoiError(f"{pre}: 'size' should be a side in pixels (1-4096), or a mapping of them")
    return cfg


def _number(v: object, low: float, high: float) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and low <= v <= high


def image_stats(src: Path, default_mean: Sequence[float], default_std: Sequence[float]) -> dict:
    """mean, std (and the raw preprocessor config) from preprocessor_config.json, else the
    defaults."""
    cfg = preprocessor(src)
    mean = [float(v) for v in cfg.get("image_mean", default_mean)]
    std = [float(v) for v in cfg.get("image_std", default_std)]
    return {"mean": mean, "std": std, "config": cfg}


#: The config.json keys that size a model, by what they count, with the range goi accepts:
#: beyond what any published checkpoint of the kinds goi exports has (ViT-H: 32 layers, 1280
#: wide; SAM and SAM 2: 1024 px; OWLv2 large: 1008 px), and small enough that building the
#: model stays finite (a config declaring 100,000 layers would be built before any weight is
#: read). A key is an integer, a list of integers (per stage) or null (the default).
_SIZED = {
    "layers": (0, 256, (
        "num_hidden_layers", "encoder_layers", "decoder_layers", "num_layers", "depths",
        "blocks_per_stage", "iou_head_depth", "memory_attention_num_layers",
        "memory_fuser_num_layers", "num_query_pool_stages", "extract_layers",
    )),
    "widths": (1, 65536, (
        "hidden_size", "intermediate_size", "projection_dim", "output_channels", "mlp_dim",
        "iou_head_hidden_dim", "d_model", "embed_dim", "encoder_ffn_dim", "decoder_ffn_dim",
        "embed_dim_per_stage", "fpn_hidden_size", "memory_attention_hidden_size",
        "memory_attention_feed_forward_hidden_size", "memory_encoder_hidden_size",
        "memory_encoder_output_channels", "mask_downsampler_embed_dim", "memory_fuser_embed_dim",
        "memory_fuser_intermediate_dim", "reduce_dim", "decoder_intermediate_size",
        "num_channels", "mask_input_channels",
    )),
    "heads": (1, 1024, (
        "num_attention_heads", "num_heads", "encoder_attention_heads", "decoder_attention_heads",
        "num_attention_heads_per_stage", "decoder_num_attention_heads",
        "memory_attention_num_attention_heads",
    )),
    "pixels": (1, 8192, (
        "image_size", "image_embedding_size", "backbone_feature_sizes",
        "memory_attention_rope_feat_sizes", "patch_size", "window_size", "patch_kernel_size",
        "window_size_per_stage", "window_positional_embedding_background_size",
        "fpn_kernel_size", "mask_downsampler_kernel_size", "memory_fuser_kernel_size",
    )),
    "tokens": (0, 1 << 20, (
        "vocab_size", "type_vocab_size", "max_position_embeddings", "max_text_len",
        "num_queries", "num_feature_levels", "num_point_embeddings", "encoder_n_points",
        "decoder_n_points",
    )),
}  # fmt: skip
_RANGES = {key: (lo, hi) for lo, hi, keys in _SIZED.values() for key in keys}


def check_config(cfg: dict, path: Path, model_type: str) -> None:
    """config.json checked before the model is built: every key that sizes the model in its
    range (naming the key), and the config's sections those of its model_type (a CLIP config
    labelled `sam` holds `text_config`, which SAM's has not)."""
    tf = transformers()
    # (the mapping is lazy: its .get answers None whatever the key)
    cls = tf.CONFIG_MAPPING[model_type] if model_type in tf.CONFIG_MAPPING else None
    subs = getattr(cls, "sub_configs", None) or {}
    for key, value in cfg.items():
        if key in subs and value is not None and not isinstance(value, dict):
            raise GoiError(f"{path}: '{key}' should be a mapping, found {type(value).__name__}")
        if not (key.endswith("_config") and isinstance(value, dict)):
            continue
        if subs and key not in subs:
            raise GoiError(
                f"{path}: model_type {model_type!r}, but it holds '{key}', which a "
                f"{model_type} config has not: is it another model's config.json?"
            )
        want = getattr(subs.get(key), "model_type", None)
        got = value.get("model_type")
        if want and got is not None and got != want:
            raise GoiError(
                f"{path}: model_type {model_type!r}, but '{key}.model_type' is {got!r}, not "
                f"{want!r}: is it another model's config.json?"
            )
    _check_sizes(cfg, path, "")


def _check_sizes(cfg: dict, path: Path, prefix: str) -> None:
    for key, value in cfg.items():
        if isinstance(value, dict):
            _check_sizes(value, path, f"{prefix}{key}.")
            continue
        if key not in _RANGES or value is None:
            continue
        lo, hi = _RANGES[key]
        flat = _ints(value)
        if flat is None or not all(lo <= v <= hi for v in flat):
            raise GoiError(
                f"{path}: '{prefix}{key}' is {str(value)[:60]}; goi exports checkpoints whose "
                f"'{key}' is an integer (or a list of them) in [{lo}, {hi}]"
            )


def _ints(value: object) -> list[int] | None:
    """The integers of an integer or a (nested) list of them, else None."""
    if isinstance(value, int) and not isinstance(value, bool):
        return [value]
    if isinstance(value, list) and len(value) <= 64:
        out: list[int] = []
        for v in value:
            sub = _ints(v)
            if sub is None:
                return None
            out += sub
        return out
    return None


def tokenizer_json(src: Path) -> str:
    """The checkpoint's fast tokenizer as tokenizer.json text: its own file, else converted by
    transformers from the slow tokenizer's files (vocab.txt, vocab.json + merges.txt, or a
    SentencePiece model). transformers builds an empty vocabulary rather than fail without
    them, so they must be there."""
    path = src / "tokenizer.json"
    if path.is_file():
        from stages.core.files import read_text

        return read_text(path, "tokenizer.json")
    slow = [("vocab.txt",), ("vocab.json", "merges.txt"), ("spiece.model",)]
    if not any(all((src / f).is_file() for f in files) for files in slow):
        raise GoiError(
            f"{path}: missing, and the checkpoint has no tokenizer vocabulary to build it from "
            "(vocab.txt, vocab.json + merges.txt, or spiece.model)"
        )
    tf = transformers()
    try:
        tok = tf.AutoTokenizer.from_pretrained(str(src), use_fast=True)
        return str(tok.backend_tokenizer.to_str())
    except Exception as e:  # transformers raises many types here
        raise GoiError(
            f"{path}: missing, and transformers could not build it from the checkpoint's "
            f"tokenizer files ({str(e).splitlines()[0][:160] if str(e) else type(e).__name__})"
        ) from None


def write_tokenizer(
    text: str, tmp: Path, name: str, max_length: int, src: Path
) -> tuple[dict, Tokens]:
    """Write a tokenizer.json into the bundle; returns its manifest entry and the tokenizer
    (for the export's checks)."""
    (tmp / name).write_text(text)
    spec = {"kind": "huggingface", "file": name, "max_length": int(max_length)}
    return spec, Tokens(tmp / name, max_length, str(src))


def image_spec(file: str, size: Sequence[int], stats: dict, **names: Any) -> dict:
    """An image graph's manifest entry: its file, `names` (its inputs' and outputs' names),
    the input size and the normalisation."""
    return {"file": file, **names, "size": list(size), "mean": stats["mean"], "std": stats["std"]}


#: A text graph's inputs: one prompt of any length.
TEXT_AXES = {"input_ids": {1: "length"}, "attention_mask": {1: "length"}}


def export_checked(
    module: Any,
    feeds: Sequence[dict[str, np.ndarray]],
    path: Path,
    outputs: Sequence[str],
    axes: dict,
    opset: int,
    fuse: Callable[[Path], int] | None = None,
) -> tuple[list[list[np.ndarray]], dict]:
    """`module` exported to `path` (its inputs named and ordered as the feeds' keys, its
    `outputs`), then run in onnxruntime against torch on every feed; returns torch's outputs
    per feed and the largest errors over the feeds. `fuse` rewrites the file's attention into
    onnxruntime's fused op (`attention.py`): the rewritten copy replaces the file when it loads
    and passes the check, and the count of layers it rewrote is recorded as `fused_attention`
    (0, with a warning, when the copy was not kept)."""
    import torch

    settle_vml()  # torch's outputs are the reference the ONNX file is held to
    with torch.no_grad():
        outs = [module(*map(torch.from_numpy, f.values())) for f in feeds]
    wants = [[t.numpy() for t in (o if isinstance(o, tuple) else (o,))] for o in outs]
    args = tuple(map(torch.from_numpy, feeds[0].values()))
    onnx_export(module, args, path, (list(feeds[0]), list(outputs)), axes, opset)
    n, found = (0, []) if fuse is None else _fused(path, fuse, feeds, wants)
    if not found:
        found = [check(path, f, w) for f, w in zip(feeds, wants, strict=True)]
    checks = {k: max(f[k] for f in found) for k in found[0]}
    return wants, checks if fuse is None else {**checks, "fused_attention": n}


def _fused(
    path: Path,
    fuse: Callable[[Path], int],
    feeds: Sequence[dict[str, np.ndarray]],
    wants: Sequence[Sequence[np.ndarray]],
) -> tuple[int, list[dict]]:
    """Fuse a copy of `path` and check it; it replaces `path` when it loads and passes. Returns
    the layers fused and the copy's checks, or (0, []) when nothing was fused or kept."""
    trial = path.with_name(f"{path.stem}.fused{path.suffix}")
    shutil.copyfile(path, trial)
    try:
        n = fuse(trial)
        found = [check(trial, f, w) for f, w in zip(feeds, wants, strict=True)] if n else []
    except Exception as e:  # onnx, onnxruntime and the check raise their own types
        trial.unlink()
        if isinstance(e, ModuleNotFoundError) and e.name == "onnx":
            raise GoiError(
                "goi export-model needs the onnx package, part of the optional extra "
                "goi[export]: pip install 'goi[export]'"
            ) from None
        why = str(e).splitlines()[0][:200] if str(e) else type(e).__name__
        warn(f"{path.name}: its attention stays as exported, the fused copy failed ({why})")
        return 0, []
    if not n:
        trial.unlink()
        return 0, []
    os.replace(trial, path)
    return n, found


def onnx_export(model: Any, args: tuple, path: Path, names: tuple, axes: dict, opset: int) -> None:
    """torch.onnx.export with TorchScript tracing (dynamo=False): the exporter every goi graph
    was checked with."""
    import torch

    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            args,
            str(path),
            input_names=list(names[0]),
            output_names=list(names[1]),
            dynamic_axes=axes,
            opset_version=opset,
            dynamo=False,
        )


def export_text_graph(
    module: Any,
    tokens: Tokens,
    path: Path,
    output: str,
    opset: int,
    texts: Sequence[str] = ("a red chair", "the lamp"),
) -> tuple[list[list[np.ndarray]], dict]:
    """A text graph (input_ids, attention_mask [1, L], L any length -> `output`), exported and
    checked on the `texts` (by default two of other lengths), as export_checked."""
    feeds = [
        dict(zip(("input_ids", "attention_mask"), tokens.encode(t), strict=True)) for t in texts
    ]
    return export_checked(module, feeds, path, [output], TEXT_AXES, opset)


def run_onnx(path: Path, feed: dict[str, np.ndarray]) -> list[np.ndarray]:
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    opts.enable_cpu_mem_arena = False  # the big graphs: see stages.models.onnx_io.session
    opts.enable_mem_pattern = False
    sess = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    return list(sess.run(None, feed))


def errors(got: Sequence[np.ndarray], want: Sequence[np.ndarray]) -> tuple[float, float, float]:
    """Largest |got - want| (infinities must coincide), largest |want| and the relative L2
    error ||got - want|| / ||want|| over the finite values, across all outputs."""
    err, ref, num, den = 0.0, 0.0, 0.0, 0.0
    for g, w in zip(got, want, strict=True):
        g, w = np.asarray(g, np.float64), np.asarray(w, np.float64)
        if g.shape != w.shape:
            return float("inf"), 0.0, float("inf")
        same_inf = np.isinf(g) & np.isinf(w) & (np.sign(g) == np.sign(w))
        d = np.where(same_inf, 0.0, np.abs(g - w))
        d = np.nan_to_num(d, nan=np.inf)
        fin = np.isfinite(w)
        if d.size:
            err = max(err, float(d.max()))
        if fin.any():
            ref = max(ref, float(np.abs(w[fin]).max()))
        num += float((d[fin] ** 2).sum()) if np.isfinite(d[fin]).all() else float("inf")
        den += float((w[fin] ** 2).sum())
    return err, ref, float(np.sqrt(num / den)) if den > 0 else float(np.sqrt(num))


def check(path: Path, feed: dict[str, np.ndarray], want: Sequence[np.ndarray]) -> dict:
    """Run the ONNX file; refuse it when it differs from torch by more than
    max(1e-3, 1e-4 x the largest output value). Returns the measured errors."""
    err, ref, rel = errors(run_onnx(path, feed), want)
    limit = max(FLOOR, TOLERANCE * ref)
    if not err <= limit:
        raise GoiError(
            f"{path.name}: ONNX output differs from torch by {err:.2e} (outputs up to "
            f"{ref:.3g}, allowed {limit:.1e})"
        )
    return {"max_abs_error": err, "max_abs_output": ref, "relative_l2_error": rel}


def check_detections(
    path: Path, feed: dict[str, np.ndarray], want: Sequence[np.ndarray], top: int = 20
) -> dict:
    """The detector's check. Raw outputs within 1e-4 x their magnitude pass as they are (the
    small test models). Otherwise what goi uses must agree: for each of torch's `top` best
    queries, an ONNX query with the same box (within 1e-3 of the image size) and the same
    score (within 1e-3)."""
    got = run_onnx(path, feed)
    err, ref, rel = errors(got, want)
    found = {"max_abs_error": err, "max_abs_output": ref, "relative_l2_error": rel}
    if err <= max(FLOOR, TOLERANCE * ref):
        return found

    def best(logits: np.ndarray) -> np.ndarray:
        with np.errstate(over="ignore"):
            return (1 / (1 + np.exp(-logits[0].astype(np.float64)))).max(-1)

    s_want, s_got = best(want[0]), best(got[0])
    b_want, b_got = np.asarray(want[1][0], np.float64), np.asarray(got[1][0], np.float64)
    worst_box, worst_score = 0.0, 0.0
    for q in np.argsort(-s_want)[:top]:
        dist = np.abs(b_got - b_want[q]).max(1) + np.abs(s_got - s_want[q])
        j = int(np.argmin(dist))
        worst_box = max(worst_box, float(np.abs(b_got[j] - b_want[q]).max()))
        worst_score = max(worst_score, float(abs(s_got[j] - s_want[q])))
    found.update(top_boxes_max_error=worst_box, top_scores_max_error=worst_score)
    if worst_box > FLOOR or worst_score > FLOOR:
        raise GoiError(
            f"{path.name}: the ONNX detector's best {top} boxes differ from torch's (boxes by "
            f"{worst_box:.2e}, scores by {worst_score:.2e}; raw outputs by {err:.2e})"
        )
    return found
