"""A ViT's self-attention in an exported graph, as onnxruntime's fused MultiHeadAttention.

The TorchScript export writes each attention as MatMul, Softmax, MatMul over a [heads, S, S]
score tensor, and onnxruntime runs those as three kernels that write the scores out and read
them back: at OWLv2-B/16's 3600 tokens, 12 x 3600 x 3600 floats a layer, and the three took
half of the image graph's time at a third of its arithmetic. onnxruntime's com.microsoft
MultiHeadAttention runs it blockwise instead (flash attention on the CPU, fused kernels on CUDA).
OWLv2-B/16 at 960 on 2 cores: 4.1 s an image against 5.0 s, outputs within 1e-6 of the unfused
graph (docs/models.md, "Fused attention").

onnxruntime's own transformer optimizer finds the attention (its CLIP pattern, which OWLv2's
vision tower shares) and writes the packed `Attention` op, whose CPU kernel is not the
blockwise one (6.5 s an image): each becomes one MatMul for Q, K and V together, a Split and a
MultiHeadAttention that adds the bias. The export's check then holds the rewritten graph to
torch like any other.

SAM 2's Hiera writes its attention on [B, S, heads, d] tensors the optimizer has no pattern
for; `fuse_hiera_attention` matches the core (transposes, MatMul, scale, Softmax, MatMul,
transpose back) itself and puts MultiHeadAttention in its place. SAM 2.1-T at 1024 on 2 cores:
see docs/models.md.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from stages.core.errors import GoiError

#: protobuf's limit on one file; a larger graph keeps its weights outside, which this rewrite
#: does not carry (the ViTs it serves are far below it)
MAX_BYTES = 2**31 - 2**26


def _onnx() -> Any:
    try:
        import onnx
    except ImportError:
        raise GoiError(
            "goi export-model needs the onnx package, part of the optional extra goi[export]: "
            "pip install 'goi[export]'"
        ) from None
    return onnx


def fuse_attention(path: Path, num_heads: int, hidden: int) -> int:
    """Rewrite the ONNX file at `path` in place; returns how many attention layers now run as
    MultiHeadAttention (0: the optimizer found none, the file is left as it was)."""
    if path.stat().st_size >= MAX_BYTES:
        return 0
    onnx = _onnx()
    from onnxruntime.transformers.optimizer import optimize_model

    # the optimizer logs each fusion it tries at INFO and WARNING
    logging.getLogger("onnxruntime.transformers").setLevel(logging.ERROR)
    opt = optimize_model(
        str(path), model_type="clip", num_heads=num_heads, hidden_size=hidden, opt_level=0
    )
    model = opt.model
    n = _packed_to_mha(model, onnx)
    if n:
        onnx.save(model, str(path))
    return n


def _packed_to_mha(model: Any, onnx: Any) -> int:
    """Each com.microsoft Attention(x, W [D, 3D], b [3D]) of `model` -> MatMul(x, W), Split into
    Q, K, V [1, S, D] and MultiHeadAttention(Q, K, V, b). A packed op with a mask, past state or
    other attributes stays as it is."""
    from onnx import helper

    graph = model.graph
    weights = {t.name: t for t in graph.initializer}
    nodes, n = [], 0
    for node in graph.node:
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        inputs = list(node.input)
        while inputs and not inputs[-1]:  # optional inputs left out may be written as ""
            inputs.pop()
        if (
            node.op_type != "Attention"
            or node.domain != "com.microsoft"
            or not set(attrs) <= {"num_heads", "scale"}
            or len(inputs) != 3
            or inputs[1] not in weights
            or len(weights[inputs[1]].dims) != 2
        ):
            nodes.append(node)
            continue
        x, w, b = inputs
        d = int(weights[w].dims[1]) // 3
        p = node.name or node.output[0]
        sizes = helper.make_tensor(f"{p}/qkv_sizes", onnx.TensorProto.INT64, [3], [d, d, d])
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
                list(node.output),
                domain="com.microsoft",
                name=f"{p}/mha",
                **attrs,
            ),
        ]
        n += 1
    del graph.node[:]
    graph.node.extend(nodes)
    return n


def fuse_hiera_attention(path: Path) -> int:
    """Rewrite the ONNX file at `path` in place: each attention of SAM 2's Hiera (and any
    graph that writes attention the same way) as one MultiHeadAttention; returns how many."""
    if path.stat().st_size >= MAX_BYTES:
        return 0
    onnx = _onnx()
    model = onnx.load(str(path))
    n = _bsnd_to_mha(model, onnx)
    if n:
        onnx.save(model, str(path))
    return n


def _bsnd_to_mha(model: Any, onnx: Any) -> int:
    """Match Transpose(q) [B, N, S, d] @ Transpose(k) [B, N, d, S] -> x scale -> Softmax ->
    (Casts) -> @ Transpose(v) -> Transpose back to [B, S, N, d], with q, k, v [B, S, N, d]
    and N read where the export split its fused QKV projection into heads; replace it by
    Reshape to [B, S, N d], MultiHeadAttention and Reshape back. What does not match exactly is
    left as it is."""
    from onnx import helper, numpy_helper

    graph = model.graph
    made = {o: node for node in graph.node for o in node.output}
    users: dict[str, list[Any]] = {}
    for node in graph.node:
        for i in node.input:
            users.setdefault(i, []).append(node)
    consts = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    for node in graph.node:
        if node.op_type == "Constant" and node.attribute and node.attribute[0].name == "value":
            consts[node.output[0]] = numpy_helper.to_array(node.attribute[0].t)

    def src(name: str) -> Any:  # the node that makes `name`, or None
        return made.get(name)

    def perm(node: Any) -> list[int] | None:
        if node is None or node.op_type != "Transpose":
            return None
        return [list(a.ints) for a in node.attribute if a.name == "perm"][0]

    def only_user(name: str) -> Any:
        u = users.get(name, [])
        return u[0] if len(u) == 1 else None

    def heads(name: str) -> int | None:
        """N where [B, S, N, d] came from Reshape(qkv, [B, S, 3, N, -1]), Split, Squeeze."""
        sq = src(name)
        split = src(sq.input[0]) if sq is not None and sq.op_type == "Squeeze" else None
        rs = src(split.input[0]) if split is not None and split.op_type == "Split" else None
        cat = src(rs.input[1]) if rs is not None and rs.op_type == "Reshape" else None
        if cat is None or cat.op_type != "Concat" or len(cat.input) < 3:
            return None
        tail = [consts.get(i) for i in cat.input[-3:]]
        if any(t is None or t.size != 1 for t in tail):
            return None
        three, n, rest = (int(np.asarray(t).ravel()[0]) for t in tail if t is not None)
        return n if three == 3 and n > 0 and rest == -1 else None

    dead: set[int] = set()
    new: list[Any] = []
    count = 0
    for sm in [x for x in graph.node if x.op_type == "Softmax"]:
        axis = [a.i for a in sm.attribute if a.name == "axis"]
        mul = src(sm.input[0])
        if axis not in ([-1], [3]) or mul is None or mul.op_type != "Mul":
            continue
        scale_in = [i for i in mul.input if i in consts and consts[i].size == 1]
        mm1 = next((src(i) for i in mul.input if i not in consts), None)
        if len(scale_in) != 1 or mm1 is None or mm1.op_type != "MatMul":
            continue
        tq, tk = src(mm1.input[0]), src(mm1.input[1])
        if perm(tq) != [0, 2, 1, 3] or perm(tk) != [0, 2, 3, 1]:
            continue
        chain, at = [], only_user(sm.output[0])
        # float32 to float32 (transformers' softmax(dtype=float32).to(q.dtype)): no-ops
        while at is not None and at.op_type == "Cast" and _cast_to(at) == onnx.TensorProto.FLOAT:
            chain.append(at)
            at = only_user(at.output[0])
        mm2 = at
        if mm2 is None or mm2.op_type != "MatMul" or mm2.input[0] != (chain or [sm])[-1].output[0]:
            continue
        tv, back = src(mm2.input[1]), only_user(mm2.output[0])
        if perm(tv) != [0, 2, 1, 3] or perm(back) != [0, 2, 1, 3]:
            continue
        n = heads(tk.input[0])
        if n is None or heads(tv.input[0]) != n:
            continue
        core = [mm1, mul, sm, *chain, mm2, back]
        core += [t for t in (tq, tk, tv) if len(users[t.output[0]]) == 1]
        dead.update(id(x) for x in core)
        p = f"{sm.name or sm.output[0]}/mha"
        flat, split = f"{p}/bsd", f"{p}/bsnd"
        graph.initializer.append(numpy_helper.from_array(np.array([0, 0, -1], np.int64), flat))
        graph.initializer.append(numpy_helper.from_array(np.array([0, 0, n, -1], np.int64), split))
        qkv = [f"{p}/{c}" for c in "qkv"]
        for t, name in zip((tq, tk, tv), qkv, strict=True):
            new.append(helper.make_node("Reshape", [t.input[0], flat], [name], name=name))
        scale = float(np.asarray(consts[scale_in[0]]).ravel()[0])
        new.append(
            helper.make_node(
                "MultiHeadAttention",
                qkv,
                [f"{p}/out"],
                domain="com.microsoft",
                name=p,
                num_heads=n,
                scale=scale,
            )  # fmt: skip
        )
        new.append(helper.make_node("Reshape", [f"{p}/out", split], list(back.output), name=split))
        count += 1
    if count:
        kept = [x for x in graph.node if id(x) not in dead]
        used = {i for x in kept + new for i in x.input} | {o.name for o in graph.output}
        kept = [x for x in kept if x.op_type != "Constant" or x.output[0] in used]
        del graph.node[:]
        graph.node.extend(kept + new)
        # ONNX wants the nodes in an order where each input is made before it is used
        _sort(graph)
    return count


def _cast_to(node: Any) -> int:
    return int(next((a.i for a in node.attribute if a.name == "to"), 0))


def _sort(graph: Any) -> None:
    """Order the nodes so that each is after the nodes whose outputs it takes (depth first)."""
    made = {o: i for i, node in enumerate(graph.node) for o in node.output}
    deps = [{made[i] for i in node.input if i in made} for node in graph.node]
    order: list[int] = []
    state = [0] * len(deps)  # 0 new, 1 on the stack, 2 placed
    for start in range(len(deps)):
        stack = [(start, iter(sorted(deps[start])))]
        if state[start]:
            continue
        state[start] = 1
        while stack:
            node, it = stack[-1]
            nxt = next((d for d in it if state[d] != 2), None)
            if nxt is None:
                stack.pop()
                state[node] = 2
                order.append(node)
            elif state[nxt] == 0:
                state[nxt] = 1
                stack.append((nxt, iter(sorted(deps[nxt]))))
    nodes = [graph.node[i] for i in order]
    del graph.node[:]
    graph.node.extend(nodes)
