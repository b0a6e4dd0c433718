"""Prompts: the one value a command makes of a prompt (`Prompt`), checking them, their
embeddings, and the file names made from prompts and views.

A prompt or a view name never becomes a path as it is: `safe_name` keeps a readable slug and
adds a hash of the full text, so names stay inside the output directory, stay short, and two
different texts never share a file. The original text is kept in the artifacts and reports.
A prompt's file name is made once, with its `Prompt`, where a command starts; the stages take
the `Prompt` and never re-derive a name from the text.
"""

from __future__ import annotations

import hashlib
import re
import unicodedata
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stages.core.arrays import normalise
from stages.core.errors import GoiError
from stages.core.files import read_json

if TYPE_CHECKING:
    from stages.models.bundle import Bundle

MAX_PROMPT_CHARS = 1000
#: Unicode categories that show nothing: separators (spaces), format marks (zero-width space,
#: direction marks) and controls.
_INVISIBLE = {"Zs", "Zl", "Zp", "Cf", "Cc"}
_SLUG = re.compile(r"[^a-z0-9]+")
_PLAIN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def check_prompt(text: str, option: str = "--prompt") -> str:
    """The prompt with surrounding blanks removed; empty, huge or binary prompts are refused."""
    t = text.strip()
    if not t:
        raise GoiError(f"{option}: the prompt is empty")
    if len(t) > MAX_PROMPT_CHARS:
        raise GoiError(f"{option}: the prompt has {len(t)} characters; at most {MAX_PROMPT_CHARS}")
    if any(unicodedata.category(c) == "Cc" and c != "\t" for c in t):
        raise GoiError(f"{option}: the prompt contains control characters (NUL, newline, DEL, ...)")
    try:
        t.encode("utf-8")
    except UnicodeEncodeError:  # a lone surrogate, e.g. undecodable bytes on the command line
        raise GoiError(
            f"{option}: the prompt is not valid Unicode text (undecodable bytes?)"
        ) from None
    if all(unicodedata.category(c) in _INVISIBLE for c in t):
        raise GoiError(
            f"{option}: the prompt has no visible character (only spaces or format marks)"
        )
    return t


def check_plain_name(name: str, option: str, names: str = "a directory") -> str:
    """A name that becomes one directory name (a prompt id): no separator, no '..', no
    control character, not blank. `names` says which directory, for the message."""
    if (
        not name.strip()
        or name in (".", "..")
        or any(c in name for c in "/\\")
        or not name.isprintable()
    ):
        raise GoiError(
            f"{option}: {name[:60]!r} is not a plain name (it names {names}: no '/', "
            "'\\', '..' or control characters)"
        )
    return name


def safe_name(text: str, max_slug: int = 40) -> str:
    """A file-name-safe, collision-free name for any text: `<slug>-<8 hex of its SHA-256>`."""
    slug = _SLUG.sub("-", text.lower()).strip("-")[:max_slug].strip("-") or "x"
    return f"{slug}-{hashlib.sha256(text.encode('utf-8', 'surrogatepass')).hexdigest()[:8]}"


def view_file_name(view: str) -> str:
    """A view's name as a file stem: itself when plain (v000, IMG_12.JPG), else safe_name."""
    return view if _PLAIN.fullmatch(view) and ".." not in view else safe_name(view)


@dataclass(frozen=True)
class Prompt:
    """One prompt, made once where a command starts (`Prompt.checked`) and passed down."""

    text: str
    """The prompt, checked (`check_prompt`): what is embedded, fitted and recorded."""
    id: str | None = None
    """Its id, when it has one (--prompt-id, a room's or a batch's prompt id): the subdirectory
    of the RES mask directory that holds its masks."""
    name: str = field(init=False, compare=False)
    """Its file name (`safe_name` of the text): OUT/<name>/, <name>.ply, its HDF5 group."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "name", safe_name(self.text))

    @classmethod
    def checked(cls, text: str, id: str | None = None, option: str = "--prompt") -> Prompt:
        """The prompt of `text` as a command takes it: checked, blanks around it removed."""
        return cls(check_prompt(text, option), id)


def load_text_embeddings(path: Path) -> dict[str, np.ndarray]:
    """`{text: [floats]}` -> unit vectors; every entry is checked."""
    raw = read_json(path, "does not exist (--text-embeddings)")
    if not isinstance(raw, dict) or not raw:
        raise GoiError(f"{path}: expected a JSON object {{text: [floats]}} with at least one entry")
    out: dict[str, np.ndarray] = {}
    dims = set()
    for text, vec in raw.items():
        v = _finite_vector(vec)
        if v is None:
            raise GoiError(f"{path}: entry {text[:60]!r} is not a list of finite numbers")
        peak = float(np.abs(v).max())
        if peak == 0:
            raise GoiError(f"{path}: entry {text[:60]!r} is the zero vector")
        out[text] = normalise(v / peak).astype(np.float32)  # scaled first: no overflow
        dims.add(v.size)
    if len(dims) > 1:
        raise GoiError(f"{path}: entries have different lengths {sorted(dims)}")
    return out


def _finite_vector(vec: object) -> np.ndarray | None:
    """[D] float64 from a JSON list of finite numbers, else None."""
    if not isinstance(vec, list) or not vec:
        return None
    try:
        if any(isinstance(x, bool) or not isinstance(x, int | float) for x in vec):
            return None
        v = np.asarray([float(x) for x in vec], np.float64)
    except OverflowError:  # an integer beyond float range
        return None
    return v if np.isfinite(v).all() else None


@dataclass(frozen=True)
class TextEmbeddings:
    """A --text-embeddings file read once (`read_text_embeddings`): its path, for messages
    and the provenance, and its unit vectors by text."""

    path: Path
    vectors: dict[str, np.ndarray]


def read_text_embeddings(path: Path) -> TextEmbeddings:
    """--text-embeddings FILE, read and checked once (a program answering many prompts)."""
    return TextEmbeddings(Path(path), load_text_embeddings(path))


def read_prompt_table(path: Path, option: str = "--prompts") -> dict[str, str]:
    """A room's prompts.json ([{id, text}, ...], other fields ignored) -> {text: id}: each
    text checked as a prompt, each id a plain name (it names the prompt's RES mask
    subdirectory); a text given twice keeps its first id."""
    raw = read_json(path, f"does not exist ({option})")
    if not isinstance(raw, list):
        raise GoiError(f"{path}: expected a JSON list of {{id, text}} prompts")
    table: dict[str, str] = {}
    for i, p in enumerate(raw):
        if not (
            isinstance(p, dict) and isinstance(p.get("id"), str) and isinstance(p.get("text"), str)
        ):
            raise GoiError(f"{path}: prompt {i} is not an object with string 'id' and 'text'")
        text = check_prompt(p["text"], f"{path}: prompt {i} 'text'")
        check_plain_name(p["id"], f"{path}: prompt {i} 'id'", "a subdirectory of --res-masks")
        table.setdefault(text, p["id"])
    return table


def text_embedding(
    prompt: str,
    dim: int,
    embeddings: Path | TextEmbeddings | None = None,
    bundle: Path | Bundle | None = None,
) -> tuple[np.ndarray, str]:
    """The prompt's unit embedding [D] and where it came from: a --text-embeddings file (a
    path, or the file already read), else a bundle's text encoder (a path, or the bundle
    already loaded)."""
    if embeddings is not None:
        if isinstance(embeddings, TextEmbeddings):
            path, vectors = embeddings.path, embeddings.vectors
        else:
            path, vectors = Path(embeddings), load_text_embeddings(embeddings)
        if prompt not in vectors:
            raise GoiError(
                f"{path}: no embedding for prompt {prompt[:80]!r} ({len(vectors)} texts "
                "listed); add it, or pass --bundle DIR with a text encoder to embed any prompt"
            )
        vec, source, where = vectors[prompt], f"file:{path.name}", str(path)
    elif bundle is not None:
        from stages.models.bundle import Bundle, load_bundle

        loaded = isinstance(bundle, Bundle)
        b = bundle if isinstance(bundle, Bundle) else load_bundle(bundle)
        vec, source = b.encode_text(prompt), f"bundle:{b.name}"
        where = str(b.root if loaded else bundle)
    else:
        raise GoiError("give --text-embeddings FILE or --bundle DIR to embed the prompt")
    if vec.shape != (dim,):
        raise GoiError(
            f"{where}: the prompt embedding has {vec.size} dimensions but the "
            f"field's codebook has {dim}; the text and image features must share one space"
        )
    return vec.astype(np.float32), source
