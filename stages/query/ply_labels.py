"""Named selections as labels in the scene's PLY (schema goi.labels_ply).

`goi export-ply --labels NAME=SELECTION.h5 ...` (and the viewer's export, through
`write_labels_ply`) writes every Gaussian of the scene unchanged, in the scene's order, followed
by two vertex properties:

- `label` int32: 0 for a Gaussian in no selection, i for one in the i-th named selection;
- `score` float32 in [0, 1]: that selection's score of the Gaussian, 0 where `label` is 0.

The names and ids are header comments, one line each, so any PLY reader skips them and the INRIA
properties stay first and untouched (splat viewers, splat-transform and INRIA's own loader read
the file as a 3DGS scene):

    comment goi schema goi.labels_ply 1.0
    comment goi provenance {"command": ..., "created": ..., "goi_version": ..., "inputs": {...}}
    comment goi overlap higher-score-then-first
    comment goi label 1 "sofa"
    comment goi label 2 "teddy bear"

A name is a JSON string with every non-ASCII character escaped, so a header stays printable
ASCII whatever the name. Where selections overlap, the Gaussian takes the label whose score is
higher, and of equal scores the one given first.

A lifted selection's score is its vote share S1 / (S1 + S0) where its evidence reaches its
`min_evidence` (the continuous score goi eval scores, `lift_math.vote_share`); every other
selected Gaussian (no lifted evidence, or a selection of the paper's one-view mode, whose
artifact records no per-Gaussian score) scores 1.0.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from stages.core.artifacts import check_writable, open_h5, provenance, sha256_file
from stages.core.errors import GoiError, warn
from stages.core.files import refuse_inputs
from stages.query.lift_math import Lifted, LiftParams, vote_share
from stages.query.selection import SCHEMA as SELECTION_SCHEMA
from stages.query.selection import load_selection
from stages.scene.gaussians import Gaussians, load_ply, save_ply

SCHEMA = "goi.labels_ply"
LABEL, SCORE = "label", "score"
#: How a Gaussian in several selections is labelled (recorded in the header).
OVERLAP = "higher-score-then-first"
#: Characters in a name: enough for a sentence-long prompt, short enough for a header line.
MAX_NAME = 200
#: Bytes the label comments may take: goi (and other readers) read a PLY header from its first
#: 64 KiB, which the INRIA properties and the scene's own extras share.
MAX_COMMENT_BYTES = 32 << 10
_LABEL_LINE = re.compile(r"goi label (\d{1,9}) (\".*\")")


class LabelLayer(NamedTuple):
    """One named selection: what the viewer hands `write_labels_ply`."""

    name: str
    selected: np.ndarray  # [G] bool
    score: np.ndarray | None = None  # [G] float in [0, 1], read where selected; None: 1.0


@dataclass
class Labels:
    """The labels of a PLY, as written or read back."""

    names: list[str]  # names[i - 1] is label i
    label: np.ndarray  # [G] int32, 0 = in no selection
    score: np.ndarray  # [G] float32 in [0, 1]
    version: str = ""
    overlap: str = OVERLAP
    provenance: dict = field(default_factory=dict)

    def counts(self) -> np.ndarray:
        """[len(names) + 1] Gaussians per label id (0 first)."""
        return np.bincount(self.label, minlength=len(self.names) + 1)


def current_version() -> str:
    from schemas import current_version as version

    return version(SCHEMA)


def _major(version: str) -> int | None:
    head = version.split(".")[0]
    return int(head) if head.isdigit() else None


def _ascii_json(obj: object) -> str:
    """JSON of printable ASCII (a header line): non-ASCII and control characters escaped."""
    return json.dumps(obj, ensure_ascii=True, sort_keys=True).replace("\x7f", "\\u007f")


def check_names(names: Sequence[str], where: str) -> None:
    """Names a user gave: non-empty, printable, without surrounding spaces, unique."""
    seen: set[str] = set()
    for name in names:
        if not name:
            raise GoiError(f"{where}: a label name is empty")
        if not name.isprintable():
            raise GoiError(f"{where}: label name {name!r} holds a character that is not printable")
        if name != name.strip():
            raise GoiError(f"{where}: label name {name!r} starts or ends with a space")
        if len(name) > MAX_NAME:
            raise GoiError(
                f"{where}: label name {name[:40]!r}... has {len(name)} characters, more than "
                f"{MAX_NAME}"
            )
        if name in seen:
            raise GoiError(f"{where}: label name {name!r} is given twice; names are unique")
        seen.add(name)


def _layer_score(layer: LabelLayer, sel: np.ndarray, where: str) -> np.ndarray:
    """[G] float32: the layer's score, checked where it selects (finite, in [0, 1])."""
    n = sel.size
    if layer.score is None:
        return np.ones(n, np.float32)
    s = np.asarray(layer.score, np.float64)
    if s.shape != (n,):
        raise GoiError(f"{where} {layer.name!r}: {s.size} scores for {n} Gaussians")
    mine = s[sel]
    if not (np.isfinite(mine).all() and (mine >= 0).all() and (mine <= 1).all()):
        raise GoiError(f"{where} {layer.name!r}: a score is not a number in [0, 1]")
    return s.astype(np.float32)


def assign(
    layers: Sequence[LabelLayer | tuple], n: int, where: str = "labels"
) -> tuple[Labels, int]:
    """The labels of `n` Gaussians from the named selections (LabelLayer or plain (name,
    selected, score | None) tuples), and how many Gaussians were in more than one (the higher
    score takes them, of equal scores the first)."""
    named = [LabelLayer(*ly) for ly in layers]
    if not named:
        raise GoiError(f"{where}: no named selection to write")
    check_names([ly.name for ly in named], where)
    label = np.zeros(n, np.int32)  # [G]
    score = np.full(n, -1.0, np.float32)  # [G] the best score so far; -1: unlabelled
    hits = np.zeros(n, np.int32)  # [G] selections holding the Gaussian
    for i, layer in enumerate(named, start=1):
        sel = np.asarray(layer.selected)
        if sel.shape != (n,) or sel.dtype != bool:
            raise GoiError(f"{where} {layer.name!r}: not a [{n}] bool selection")
        s = _layer_score(layer, sel, where)
        take = sel & (s > score)  # strict: of equal scores the earlier label stays
        label[take] = i
        score[take] = s[take]
        hits += sel
    score[label == 0] = 0.0
    labels = Labels([ly.name for ly in named], label, score, current_version())
    return labels, int((hits > 1).sum())


def label_comments(
    names: Sequence[str], inputs: dict[str, str], where: str = "labels"
) -> list[str]:
    """The header comments of a labels PLY (without the 'comment ' keyword)."""
    prov = {**provenance(inputs), "inputs": inputs}
    lines = [
        f"goi schema {SCHEMA} {current_version()}",
        f"goi provenance {_ascii_json(prov)}",
        f"goi overlap {OVERLAP}",
        *(f"goi label {i} {_ascii_json(name)}" for i, name in enumerate(names, start=1)),
    ]
    size = sum(len(c) + len("comment \n") for c in lines)
    if size > MAX_COMMENT_BYTES:
        raise GoiError(
            f"{where}: the {len(names)} names and the provenance take {size} bytes of the PLY "
            f"header, more than {MAX_COMMENT_BYTES} (PLY readers read a header from its first "
            "64 KiB); give fewer or shorter names"
        )
    return lines


def labelled_vertex(vertex: np.ndarray, label: np.ndarray, score: np.ndarray) -> np.ndarray:
    """The vertex table with `label` and `score` last (a scene's own are replaced)."""
    names = vertex.dtype.names or ()
    clash = [n for n in (LABEL, SCORE) if n in names]
    if clash:
        shown = " and ".join(f"'{n}'" for n in clash)
        warn(f"the scene's own {shown} properties are replaced by the labels")
    kept = [n for n in names if n not in clash]
    # field by field: numpy's recfunctions.append_fields walks the records in Python
    out = np.empty(
        len(vertex), [(n, vertex.dtype[n]) for n in kept] + [(LABEL, "i4"), (SCORE, "f4")]
    )
    for n in kept:
        out[n] = vertex[n]
    out[LABEL] = label
    out[SCORE] = score
    return out


def write_labels_ply(
    g: Gaussians,
    layers: Sequence[LabelLayer | tuple],
    out: Path,
    inputs: dict[str, str],
    force: bool = False,
    where: str = "labels",
) -> tuple[Path, Labels, int]:
    """Write the scene `g` with the labels of `layers` (the viewer's export; `goi export-ply
    --labels` comes here too). `inputs` maps a role ('ply', ...) to a SHA-256 for the
    provenance. Returns the path, the labels and the number of Gaussians in several layers."""
    check_writable(out, force, "--out")
    refuse_inputs({"--out": out}, [g.path])
    labels, overlapping = assign(layers, len(g.vertex), where)
    comments = label_comments(labels.names, inputs, where)
    save_ply(out, labelled_vertex(g.vertex, labels.label, labels.score), force, comments)
    return Path(out), labels, overlapping


def parse_spec(text: str) -> tuple[str, Path]:
    """--labels NAME=SELECTION.h5 -> (name, path); the name ends at the first '='."""
    name, eq, path = text.partition("=")
    if not eq or not path:
        raise GoiError(f"--labels: {text!r} is not NAME=SELECTION.h5")
    check_names([name], f"--labels {text!r}")
    return name, Path(path)


def selection_layer(name: str, path: Path, ply_sha: str, n: int) -> LabelLayer:
    """A goi.selection artifact as a layer, refused unless made on this PLY; a lifted one
    scores its Gaussians by its vote share (the module doc)."""
    where = f"--labels {name}={path}"
    sel = load_selection(path)
    if sel.ply_sha256 != ply_sha:
        raise GoiError(
            f"{where}: it was made for another PLY (sha256 {sel.ply_sha256[:12]}...); "
            "select again on this scene"
        )
    if sel.selected.size != n:
        raise GoiError(f"{where}: {sel.selected.size} Gaussians, the PLY has {n}")
    refinement = (sel.lifted or {}).get("refinement") or {}
    if refinement.get("final") is False:
        warn(
            f"{where}: a refining answer ({refinement.get('n_views')} of "
            f"{refinement.get('of')} views), not the final one"
        )
    with open_h5(path, SELECTION_SCHEMA) as f:
        if "lifted/S1" not in f or "lifted/S0" not in f:
            return LabelLayer(name, sel.selected)
        S1 = f["lifted/S1"][()].astype(np.float64)
        S0 = f["lifted/S0"][()].astype(np.float64)
    if not (np.isfinite(S1).all() and np.isfinite(S0).all() and S1.min() >= 0 and S0.min() >= 0):
        raise GoiError(f"{path}: lifted/S1 or lifted/S0 holds a negative or non-finite value")
    params = (sel.lifted or {}).get("params") or {}
    tau = params.get("min_evidence", LiftParams().min_evidence)
    if isinstance(tau, bool) or not isinstance(tau, int | float) or not tau >= 0:
        raise GoiError(f"{path}: the lifted record's min_evidence {tau!r} is not a number >= 0")
    lifted = Lifted(sel.selected, S1 + S0 >= tau, S1, S0, {})
    ones = np.ones(n, np.float32)  # no evidence: the artifact records no score
    return LabelLayer(name, sel.selected, vote_share(lifted, LiftParams(min_evidence=tau), ones))


def export_labels(
    g: Gaussians,
    ply_sha: str,
    specs: Sequence[str],
    out: Path,
    force: bool = False,
) -> tuple[Path, Labels, int]:
    """`goi export-ply --labels NAME=SELECTION.h5 ...`: the scene with the named selections'
    labels; see write_labels_ply."""
    check_writable(out, force, "--out")
    parsed = [parse_spec(s) for s in specs]
    check_names([name for name, _ in parsed], "--labels")
    refuse_inputs({"--out": out}, [g.path, *(p for _, p in parsed)])
    layers = [selection_layer(name, p, ply_sha, len(g.vertex)) for name, p in parsed]
    inputs = {"ply": ply_sha}
    inputs.update({f"label {i}": sha256_file(p) for i, (_, p) in enumerate(parsed, start=1)})
    return write_labels_ply(g, layers, out, inputs, force, "--labels")


# -- reading ------------------------------------------------------------------------------


def goi_comments(g: Gaussians) -> list[str]:
    """The header comments goi wrote (those a rewrite of the labelled scene carries)."""
    return [c for c in g.comments if c.startswith("goi ")]


def labels_of(g: Gaussians) -> Labels | None:
    """The labels of a loaded PLY, checked; None when it is no labels PLY (no goi schema
    comment). Refuses a malformed one with a message naming the file."""
    p = g.path
    schemas = [c.split()[2:] for c in g.comments if c.startswith("goi schema ")]
    if not schemas:
        return None
    if len(schemas) > 1 or len(schemas[0]) != 2 or schemas[0][0] != SCHEMA:
        raise GoiError(f"{p}: a 'comment goi schema' line is not '{SCHEMA} MAJOR.MINOR' (once)")
    version = schemas[0][1]
    ours = current_version()
    if _major(version) != _major(ours):
        newer = (_major(version) or 0) > (_major(ours) or 0)
        raise GoiError(
            f"{p}: {SCHEMA} version {version} is not readable by goi's {ours}: "
            + ("upgrade goi to read it" if newer else "write it again with this goi")
        )
    names: list[str] = []
    overlap, prov = "", {}
    for c in g.comments:
        if c.startswith("goi label "):
            m = _LABEL_LINE.fullmatch(c)
            try:
                name = json.loads(m.group(2)) if m else None
            except ValueError:
                name = None
            if m is None or not isinstance(name, str) or int(m.group(1)) != len(names) + 1:
                raise GoiError(
                    f"{p}: header comment {c[:80]!r} is not 'goi label {len(names) + 1} "
                    '"NAME"\' (ids run 1, 2, ... in order)'
                )
            names.append(name)
        elif c.startswith("goi overlap "):
            overlap = c[len("goi overlap ") :]
        elif c.startswith("goi provenance "):
            try:
                prov = json.loads(c[len("goi provenance ") :])
            except ValueError:
                raise GoiError(f"{p}: the 'goi provenance' comment is not JSON") from None
    if not names:
        raise GoiError(f"{p}: names no label (no 'comment goi label 1 \"NAME\"' line)")
    check_names(names, str(p))
    v = g.vertex
    fields = v.dtype.names or ()
    for name, kind, what in ((LABEL, "iu", "an integer"), (SCORE, "f", "a float")):
        if name not in fields:
            raise GoiError(f"{p}: vertex property '{name}' is missing")
        if v.dtype[name].kind not in kind:
            raise GoiError(f"{p}: vertex property '{name}' is {v.dtype[name]}, not {what}")
    label = np.asarray(v[LABEL])
    bad = (label < 0) | (label > len(names))
    if bad.any():
        i = int(np.argmax(bad))
        raise GoiError(
            f"{p}: label {int(label[i])} at vertex {i} is not one of the ids 0..{len(names)} "
            "the header names"
        )
    score = np.asarray(v[SCORE], np.float32)
    bad = ~(np.isfinite(score) & (score >= 0) & (score <= 1))
    if bad.any():
        i = int(np.argmax(bad))
        raise GoiError(f"{p}: score {float(score[i])!r} at vertex {i} is not a number in [0, 1]")
    return Labels(names, label.astype(np.int32), score, version, overlap, prov)


def read_labels(path: str | os.PathLike[str]) -> Labels:
    """The named labels of a labels PLY (goi export-ply --labels), checked."""
    g = load_ply(path)
    labels = labels_of(g)
    if labels is None:
        rewritten = LABEL in (g.vertex.dtype.names or ())
        raise GoiError(
            f"{g.path}: not a goi labels PLY (no 'comment goi schema {SCHEMA}' header line)"
            + (
                "; its 'label' property has no names: a tool that rewrote the file dropped "
                "goi's header comments"
                if rewritten
                else ""
            )
        )
    return labels
