"""onnxruntime sessions, tensor checks and tokenizers for the models of a bundle.

Every model file is opened here: a path may not leave its bundle directory, a file that
onnxruntime cannot load is a clean error, and each tensor a manifest names is checked (name,
rank, fixed sizes) before the model runs, with a message naming the file and the tensor.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from stages.core.errors import GoiError, warn
from stages.core.files import regular_file


def providers() -> list[str]:
    import onnxruntime as ort

    have = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in have]


def inside(root: Path, rel: str, where: str) -> Path:
    """A file named by a manifest: inside the bundle directory, and present."""
    p = (root / rel).resolve()
    if not p.is_relative_to(root.resolve()):
        raise GoiError(f"{where}: path {rel!r} points outside the bundle directory")
    if not p.is_file():
        raise GoiError(f"{where}: {rel} is missing from the bundle")
    return p


#: onnxruntime's intra-op threads for the sessions opened from now on (None: its default, one
#: per core). Several processes on one machine each set fewer (`goi index-res --threads`).
_THREADS: list[int | None] = [None]


def set_threads(n: int | None) -> None:
    """Threads of each onnxruntime session opened from now on (None: onnxruntime's default)."""
    _THREADS[0] = n


#: Model files from this size on are large graphs for `session(low_memory=True)`.
LOW_MEMORY_FROM_BYTES = 200 << 20


def session(path: Path, low_memory: bool = False) -> Session:
    """An onnxruntime session. `low_memory`, for a graph of LOW_MEMORY_FROM_BYTES or more,
    turns off the CPU memory arena and the memory-pattern planner: the large RES graphs (SAM's
    ViT encoder, Grounding DINO) otherwise keep several GB of peak activations reserved (SAM
    ViT-B's encoder passed 7 GB with them, 4 GB without), at a cost of a few percent in speed.
    A small graph keeps them: SAM 2.1-T's encoder (109 MB) peaks at 1.5 GB with them and 1.25 GB
    without, and runs 14 % faster with them (1.70 s against 1.98 s at 1024 px, 2 cores)."""
    import onnxruntime as ort

    # onnxruntime logs a failing kernel on stderr itself: goi's one line says it instead
    ort.set_default_logger_severity(4)
    opts = ort.SessionOptions()
    opts.log_severity_level = 4
    # onnxruntime's idle threads spin for work after a run by default, and goi runs its numba
    # kernels (lifting, masks) between the runs of a prompt: the spinning threads took the
    # cores from them (a second prompt on 8 indexed views, 2 cores: 2.10 s spinning, 1.91 s
    # not; a model's own run is the same within 2 %)
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if _THREADS[0] is not None:
        opts.intra_op_num_threads = _THREADS[0]
        opts.inter_op_num_threads = 1
    if low_memory and path.stat().st_size >= LOW_MEMORY_FROM_BYTES:
        opts.enable_cpu_mem_arena = False
        opts.enable_mem_pattern = False
    try:
        inner = ort.InferenceSession(str(path), sess_options=opts, providers=providers())
    except Exception as e:  # onnxruntime raises its own exception types for bad models
        raise GoiError(
            f"{path}: not a loadable ONNX model ({str(e).splitlines()[0][:200]})"
        ) from None
    return Session(inner, path)


class Session:
    """An onnxruntime session whose every run is checked: a model that fails while it runs
    (a shape its graph cannot take, a kernel error) is a GoiError naming the file, the
    outputs asked for and the tensors fed, never onnxruntime's own exception or log line."""

    def __init__(self, inner: Any, path: Path):
        self.inner = inner
        self.path = path

    def get_inputs(self) -> Any:
        return self.inner.get_inputs()

    def get_outputs(self) -> Any:
        return self.inner.get_outputs()

    def run(self, outputs: list[str], feed: dict[str, np.ndarray]) -> list[np.ndarray]:
        import onnxruntime as ort

        opts = ort.RunOptions()
        opts.log_severity_level = 4
        try:
            return list(self.inner.run(outputs, feed, opts))
        except Exception as e:  # onnxruntime's own exception types
            fed = ", ".join(
                f"'{k}' {list(np.shape(v))} {np.asarray(v).dtype}" for k, v in feed.items()
            )
            first = (str(e).strip().splitlines() or [type(e).__name__])[0]
            raise GoiError(
                f"{self.path}: the model failed while computing "
                f"{', '.join(repr(o) for o in outputs)} from {fed} ({first[:240]})"
            ) from None


def check_io(
    sess: Any, path: Path, kind: str, name: str, rank: int, fixed: dict[int, int] | None = None
) -> list[int | str]:
    """The named input or output exists with the expected rank and fixed dimensions; returns
    its shape (ints for fixed sizes, names for dynamic ones)."""
    items = sess.get_inputs() if kind == "input" else sess.get_outputs()
    found = {i.name: i for i in items}
    if name not in found:
        raise GoiError(f"{path}: no {kind} named '{name}' (it has: {', '.join(found)})")
    shape = list(found[name].shape)
    if len(shape) != rank:
        raise GoiError(f"{path}: {kind} '{name}' has rank {len(shape)} {shape}, expected {rank}")
    for axis, size in (fixed or {}).items():
        if isinstance(shape[axis], int) and shape[axis] != size:
            raise GoiError(
                f"{path}: {kind} '{name}' has size {shape[axis]} on axis {axis}, expected {size}"
            )
    return shape


def check_inputs_named(sess: Any, path: Path, named: list[str]) -> None:
    """The graph needs no input beyond those the manifest names (goi could not feed it)."""
    extra = [i.name for i in sess.get_inputs() if i.name not in named]
    if extra:
        raise GoiError(f"{path}: input '{extra[0]}' is not named in the manifest")


class Tokens:
    """A Hugging Face tokenizer.json with the model's length limit: longer prompts are cut
    to it, with a warning."""

    def __init__(self, path: Path, max_length: int, where: str):
        from tokenizers import Tokenizer

        regular_file(path, "tokenizer.json")
        try:
            self.tok = Tokenizer.from_file(str(path))
        except Exception as e:  # tokenizers raises its own exception type
            raise GoiError(f"{path}: not a tokenizer.json ({str(e)[:200]})") from None
        if max_length < 2:
            raise GoiError(f"{where}: tokenizer max_length {max_length} is below 2")
        self.tok.no_padding()
        self.tok.enable_truncation(max_length)
        self.max_length = max_length
        self.path = path

    def encode(self, text: str) -> tuple[np.ndarray, np.ndarray]:
        """-> input_ids and attention_mask, both [1, L] int64."""
        enc = self.tok.encode(text)
        if enc.overflowing:
            warn(
                f"the prompt {text[:60]!r} is longer than the model's {self.max_length} tokens "
                f"({self.path.name}); it was cut to them"
            )
        ids = np.asarray([enc.ids], np.int64)
        return ids, np.asarray([enc.attention_mask], np.int64)


def checked_embedding(v: np.ndarray, where: str) -> np.ndarray:
    """A text encoder's output [D] as a unit vector; a NaN, infinite or zero embedding (a
    broken model) is refused, as a zero vector in --text-embeddings is."""
    from stages.core.arrays import normalise

    if v.ndim != 1 or not np.isfinite(v).all():
        raise GoiError(f"{where}: the text encoder returned NaN or infinite values")
    top = float(np.abs(v).max(initial=0.0))
    if not top > 0:
        raise GoiError(f"{where}: the text encoder returned a zero embedding (no direction)")
    return normalise(v / top)  # scaled first: a tiny vector keeps its direction exactly
