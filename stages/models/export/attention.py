"""A ViT's self-attention in an exported graph, as onnxruntime's fused MultiHeadAttention.

The TorchScript export writes each attention as MatMul, Softmax, MatMul over a [heads, S, S]
score tensor, and onnxruntime runs those as three kernels that write the scores out and read
them back: at OWLv2-B/16's 3600 tokens, 12 x 3600 x 3600 floats a layer, and the three took
half of the image graph's time at a third of its arithmetic. onnxruntime's com.microsoft
MultiHeadAttention runs it blockwise instead (flash attention on the CPU, fused kernels on CUDA).
OWLv2-B/16 at 960 on 2 cores: 4.1 s an image against 5.0 s, outputs within 2e-6 of the unfused
graph (docs/models.md, "Fused attention").

onnxruntime's own transformer optimizer finds the attention (its CLIP pattern, which OWLv2's
vision tower shares) and writes the packed `Attention` op, whose CPU kernel is not the
blockwise one (6.5 s an image): each becomes one MatMul for Q, K and V together, a Split and a
MultiHeadAttention that adds the bias. The optimizer's other fusions (LayerNorm with the
residual add, GELU with its bias) are kept too: onnxruntime makes the same ones when it loads a
graph. `export_checked` fuses a copy and keeps it only when it loads and passes the check
against torch; otherwise the graph stays as exported, with a warning.

SAM 2's Hiera writes its attention on [B, S, heads, d] tensors the optimizer has no pattern
for; `fuse_hiera_attention` matches the core (transposes, MatMul, scale, Softmax, MatMul,
transpose back) itself and puts MultiHeadAttention in its place. SAM 2.1-T at 1024 on 2 cores:
see docs/models.md.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

#: protobuf's limit on one file; a larger graph keeps its weights outside, which this rewrite
#: does not carry (the ViTs it serves are far below it)
MAX_BYTES = 2**31 - 2**26
MS_DOMAIN = "com.microsoft"


@contextmanager
def _quiet() -> Iterator[None]:
    """onnxruntime's fusion modules log each pattern they try (under their own module names)."""
    before = logging.root.manager.disable
    logging.disable(logging.WARNING)
    try:
        yield
    finally:
        logging.disable(before)


def fuse_attention(path: Path, num_heads: int, hidden: int) -> int:
    """Rewrite the ONNX file at `path` in place; returns how many attention layers now run as
    MultiHeadAttention (0: the optimizer found none, the file is left as it was). Needs the
    onnx package (ImportError without it)."""
    if path.stat().st_size >= MAX_BYTES:
        return 0
    import onnx
    from onnxruntime.transformers.optimizer import optimize_model

    with _quiet():
        opt = optimize_model(
            str(path), model_type="clip", num_heads=num_heads, hidden_size=hidden, opt_level=0
        )
    model = opt.model
    n = _packed_to_mha(model)
    if n:
        _declare_ms_domain(model)
        onnx.save(model, str(path))
    return n


def _declare_ms_domain(model: Any) -> None:
    from onnx import helper

    if not any(o.domain == MS_DOMAIN for o in model.opset_import):
        model.opset_import.append(helper.make_opsetid(MS_DOMAIN, 1))


def _packed_to_mha(model: Any) -> int:
    """Each com.microsoft Attention(x, W [D, 3D], b [3D]) -> its output of `model` becomes
    MatMul(x, W), Split into Q, K, V [1, S, D] and MultiHeadAttention(Q, K, V, b). A packed op
    with a mask, past state, a second output or other attributes stays as it is."""
    from onnx import TensorProto, helper

    graph = model.graph
    weights = {t.name: t for t in graph.initializer}
    nodes, n = [], 0
    for node in graph.node:
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        inputs = list(node.input)
        while inputs and not inputs[-1]:  # optional inputs left out may be written as ""
            inputs.pop()
        outputs = [o for o in node.output if o]
        if (
            node.op_type != "Attention"
            or node.domain != MS_DOMAIN
            or not set(attrs) <= {"num_heads", "scale"}
            or len(inputs) != 3
            or outputs != list(node.output[:1])
            or inputs[1] not in weights
            or len(weights[inputs[1]].dims) != 2
        ):
            nodes.append(node)
            continue
        x, w, b = inputs
        d = int(weights[w].dims[1]) // 3
        p = node.name or node.output[0]
        sizes = helper.make_tensor(f"{p}/qkv_sizes", TensorProto.INT64, [3], [d, d, d])
        graph.initializer.append(sizes)
        q, k, v = f"{p}/q", f"{p}/k", f"{p}/v"
        nodes += [
            helper.make_node("MatMul", [x, w], [f"{p}/qkv"], name=f"{p}/qkv"),
            helper.make_node(
                "Split", [f"{p}/qkv", sizes.name], [q, k, v], axis=-1, name=f"{p}/split"
            ),
            helper.make_node(
                "MultiHeadAttention",
                [q, k, v, b],
                outputs,
                domain=MS_DOMAIN,
                name=f"{p}/mha",
                **attrs,
            ),  # fmt: skip
        ]
        n += 1
    del graph.node[:]
    graph.node.extend(nodes)
    return n


def fuse_hiera_attention(path: Path) -> int:
    """Rewrite the ONNX file at `path` in place: each attention of SAM 2's Hiera (and any
    graph that writes attention the same way) as one MultiHeadAttention; returns how many.
    Needs the onnx package (ImportError without it)."""
    if path.stat().st_size >= MAX_BYTES:
        return 0
    import onnx

    model = onnx.load(str(path))
    n = _bsnd_to_mha(model)
    if n:
        _declare_ms_domain(model)
        onnx.save(model, str(path))
    return n


def _perm(node: Any) -> list[int] | None:
    """A Transpose's permutation (none given: the axes reversed, as ONNX says), else None."""
    if node is None or node.op_type != "Transpose":
        return None
    given = next((list(a.ints) for a in node.attribute if a.name == "perm"), None)
    return given if given is not None else [3, 2, 1, 0]


def _read_inside(nodes: list[Any]) -> list[str]:
    """Every name the subgraphs of `nodes` (If, Loop) read, at any depth: they may read the
    outer graph's tensors by name."""
    from onnx import AttributeProto

    names: list[str] = []
    for node in nodes:
        for a in node.attribute:
            if a.type == AttributeProto.GRAPH:
                graphs = [a.g]
            elif a.type == AttributeProto.GRAPHS:
                graphs = list(a.graphs)
            else:
                continue
            for g in graphs:
                names += [i for n in g.node for i in n.input if i]
                names += _read_inside(list(g.node))
    return names


def _cast_to(node: Any) -> int:
    return int(next((a.i for a in node.attribute if a.name == "to"), 0))


def _bsnd_to_mha(model: Any) -> int:
    """Match Transpose(q) [B, N, S, d] @ Transpose(k) [B, N, d, S] -> x scale -> Softmax ->
    (Casts) -> @ Transpose(v) -> Transpose back to [B, S, N, d], with q, k, v [B, S, N, d]
    and N read where the export split its fused QKV projection into heads; replace it by
    Reshape to [B, S, N d], MultiHeadAttention and Reshape back, where the last transpose
    was (every input the new nodes take is made before it). Every tensor inside the match must
    have no other reader, a graph output or a subgraph's read included."""
    from onnx import TensorProto, helper, numpy_helper

    graph = model.graph
    # one list of the nodes: protobuf may hand out a new wrapper at each graph.node[i], and
    # the match compares nodes by identity
    every = list(graph.node)
    made = {o: i for i, node in enumerate(every) for o in node.output if o}
    readers: dict[str, list[int]] = {}
    for i, node in enumerate(every):
        for name in node.input:
            if name:
                readers.setdefault(name, []).append(i)
    # what the graph's outputs and its subgraphs (If, Loop) read counts as read elsewhere
    for name in [o.name for o in graph.output] + _read_inside(every):
        readers.setdefault(name, []).append(-1)
    consts = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    for node in every:
        if node.op_type == "Constant" and node.attribute and node.attribute[0].name == "value":
            consts[node.output[0]] = numpy_helper.to_array(node.attribute[0].t)

    def src(name: str) -> Any:  # typed Any: the node that makes `name`, or None
        i = made.get(name)
        return None if i is None else every[i]

    def sole(name: str) -> Any:
        """The one node that reads `name` (a graph output counts as a reader), or None."""
        r = readers.get(name, [])
        return every[r[0]] if len(r) == 1 and r[0] >= 0 else None

    def heads(name: str) -> int | None:
        """N where [B, S, N, d] came from Reshape(qkv, [B, S, 3, N, -1]), Split, Squeeze."""
        sq = src(name)
        split = src(sq.input[0]) if sq is not None and sq.op_type == "Squeeze" else None
        rs = src(split.input[0]) if split is not None and split.op_type == "Split" else None
        if rs is None or rs.op_type != "Reshape":
            return None
        if rs.input[1] in consts:  # a shape the exporter folded
            tail = list(np.asarray(consts[rs.input[1]]).ravel()[-3:])
        else:
            cat = src(rs.input[1])
            if cat is None or cat.op_type != "Concat" or len(cat.input) < 3:
                return None
            parts = [consts.get(i) for i in cat.input[-3:]]
            if any(t is None or t.size != 1 for t in parts):
                return None
            tail = [np.asarray(t).ravel()[0] for t in parts if t is not None]
        if len(tail) != 3:
            return None
        three, n, rest = (int(v) for v in tail)
        return n if three == 3 and n > 0 and rest == -1 else None

    dead: set[int] = set()
    at_back: dict[int, list[Any]] = {}  # the new nodes, by the index of the transpose back
    for sm in [x for x in every if x.op_type == "Softmax"]:
        axis = [a.i for a in sm.attribute if a.name == "axis"]
        mul = src(sm.input[0])
        if axis not in ([-1], [3]) or mul is None or mul.op_type != "Mul":
            continue
        scale_in = [i for i in mul.input if i in consts and consts[i].size == 1]
        mm1 = next((src(i) for i in mul.input if i not in consts), None)
        if len(scale_in) != 1 or mm1 is None or mm1.op_type != "MatMul":
            continue
        if sole(mm1.output[0]) is not mul or sole(mul.output[0]) is not sm:
            continue
        tq, tk = src(mm1.input[0]), src(mm1.input[1])
        if _perm(tq) != [0, 2, 1, 3] or _perm(tk) != [0, 2, 3, 1]:
            continue
        chain, at = [], sole(sm.output[0])
        # float32 to float32 (transformers' softmax(dtype=float32).to(q.dtype)): no-ops
        while at is not None and at.op_type == "Cast" and _cast_to(at) == TensorProto.FLOAT:
            chain.append(at)
            at = sole(at.output[0])
        mm2 = at
        if mm2 is None or mm2.op_type != "MatMul" or mm2.input[0] != (chain or [sm])[-1].output[0]:
            continue
        tv, back = src(mm2.input[1]), sole(mm2.output[0])
        if _perm(tv) != [0, 2, 1, 3] or _perm(back) != [0, 2, 1, 3]:
            continue
        n = heads(tk.input[0])
        if n is None or heads(tv.input[0]) != n:
            continue
        core = [mm1, mul, sm, *chain, mm2, back]
        core += [t for t in (tq, tk, tv) if len(readers[t.output[0]]) == 1]
        dead.update(made[x.output[0]] for x in core)
        p = f"{sm.name or sm.output[0]}/mha"
        flat, split = f"{p}/bsd", f"{p}/bsnd"
        graph.initializer.append(numpy_helper.from_array(np.array([0, 0, -1], np.int64), flat))
        graph.initializer.append(numpy_helper.from_array(np.array([0, 0, n, -1], np.int64), split))
        qkv = [f"{p}/{c}" for c in "qkv"]
        scale = float(np.asarray(consts[scale_in[0]]).ravel()[0])
        at_back[made[back.output[0]]] = [
            *(helper.make_node("Reshape", [t.input[0], flat], [name], name=name)
              for t, name in zip((tq, tk, tv), qkv, strict=True)),
            helper.make_node("MultiHeadAttention", qkv, [f"{p}/out"], domain=MS_DOMAIN, name=p,
                             num_heads=n, scale=scale),
            helper.make_node("Reshape", [f"{p}/out", split], list(back.output), name=split),
        ]  # fmt: skip
    if not at_back:
        return 0
    gone = {name for i in dead for name in every[i].input}
    nodes: list[Any] = []
    for i, node in enumerate(every):
        if i in at_back:
            nodes += at_back[i]
        elif i not in dead:
            nodes.append(node)
    # the scale constants the removed Muls read, when nothing else reads them
    read = {name for node in nodes for name in node.input} | {o.name for o in graph.output}
    read |= set(_read_inside(nodes))
    unread = gone - read
    nodes = [x for x in nodes if not (x.op_type == "Constant" and x.output[0] in unread)]
    kept = [t for t in graph.initializer if t.name not in unread]
    del graph.node[:]
    graph.node.extend(nodes)
    del graph.initializer[:]
    graph.initializer.extend(kept)
    return len(at_back)
