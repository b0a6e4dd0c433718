"""Property-based tests of the artifacts' contents: files that pass their schema but hold
arbitrary values, shapes and cross-references. A reader either returns something every later
step can use, or refuses with a GoiError; it never raises anything else, and what it returns
never makes a later step fail."""

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stages.core.artifacts import put, write_h5
from stages.core.errors import GoiError
from stages.query.hyperplanes import load_plane, read_hyperplanes
from stages.query.prompts import safe_name
from stages.query.selection import load_selection
from stages.semantics.blend_cache import BlendCache
from stages.semantics.feature_renderer import FeatureRenderer
from stages.semantics.field import load_field

CONTENTS = settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
#: float32 values, the odd ones included
VALUES = st.floats(allow_nan=True, allow_infinity=True, width=32)


def _array(draw, shape) -> np.ndarray:
    n = int(np.prod(shape))
    plain = st.floats(-4, 4, width=32)
    values = draw(st.lists(st.one_of(plain, VALUES) if draw(st.booleans()) else plain,
                           min_size=n, max_size=n))  # fmt: skip
    return np.asarray(values, np.float32).reshape(shape)


def _path(tmp_path_factory, name: str) -> Path:
    return tmp_path_factory.mktemp("art") / name


@st.composite
def fields(draw):
    g, s = draw(st.integers(1, 12)), draw(st.integers(1, 4))
    n, d = draw(st.integers(0, 6)), draw(st.integers(1, 5))
    direct = draw(st.booleans())
    out = draw(st.integers(0, 8))
    return {
        "features": _array(draw, (g, s)),
        "decoder_weight": _array(draw, (out, s)),
        "decoder_bias": _array(draw, (out,)),
        "codebook": _array(draw, (n, d)),
        "decoder": "direct" if direct else "codebook",
    }


@CONTENTS
@given(fields())
def test_field_reader_on_arbitrary_contents(tmp_path_factory, doc):
    p = _path(tmp_path_factory, "field.h5")
    g, s = doc["features"].shape
    n, d = doc["codebook"].shape
    with write_h5(p, "goi.field", {"ply": "x"}) as f:
        f.attrs.update(n_gaussians=g, sem_dim=s, n_entries=n, dim=d, iterations=1, seed=0,
                       config=json.dumps({}), ply_sha256="x", decoder=doc["decoder"])  # fmt: skip
        for name in ("features", "decoder_weight", "decoder_bias", "codebook"):
            put(f, name, doc[name])
        put(f, "loss_curve", np.zeros((1, 5), np.float32))
        put(f, "views", np.array(["v"], dtype=object))
    try:
        field = load_field(p)
    except GoiError:
        return
    for a in (field.features, field.decoder_weight, field.decoder_bias, field.codebook):
        assert np.isfinite(a).all()
    if field.direct:
        assert field.decode_direct(field.features).shape == (g, d)
    else:
        idx = field.decode_index(field.features)
        assert ((0 <= idx) & (idx < n)).all()


@st.composite
def planes(draw):
    k = draw(st.integers(1, 3))
    out = []
    for i in range(k):
        d, n = draw(st.integers(1, 5)), draw(st.integers(0, 6))
        dt = draw(st.sampled_from([d, d, d + 1]))  # the text embedding may not fit W
        out.append((f"p{i}", _array(draw, (d,)), _array(draw, (n,)), _array(draw, (dt,)),
                    draw(VALUES)))  # fmt: skip
    return out


@CONTENTS
@given(planes(), st.integers(1, 6))
def test_hyperplanes_reader_on_arbitrary_contents(tmp_path_factory, doc, n_entries):
    root = tmp_path_factory.mktemp("planes")
    p, field_path = root / "planes.h5", root / "field.h5"
    field_path.write_bytes(b"stands for the field")
    from stages.core.artifacts import sha256_file

    with write_h5(p, "goi.hyperplanes", {"field": "x"}) as f:
        grp = f.create_group("prompts")
        for prompt, W, scores, text, b in doc:
            g = grp.create_group(safe_name(prompt))
            g.attrs.update(prompt=prompt, b=float(b), text_source="t", mask_source="m",
                           views="[]", field_sha256=sha256_file(field_path), fit_key="k",
                           config="{}", res_iou_init=0.0, res_iou=0.0, steps_run=0,
                           best_step=0)  # fmt: skip
            put(g, "W", W)
            put(g, "entry_scores", scores)
            put(g, "text_embedding", text)
    try:
        read = read_hyperplanes(p)
    except GoiError:
        return
    for plane in read.values():
        assert np.isfinite(plane.W).all() and np.isfinite(plane.scores).all()
        assert np.isfinite(plane.b)
        try:
            loaded = load_plane(p, plane.prompt, field_path, n_entries)
        except GoiError:
            assert plane.scores.size != n_entries
            continue
        assert loaded.positive.shape == (n_entries,)


@st.composite
def caches(draw):
    n_g = draw(st.integers(1, 8))
    w, h = draw(st.integers(1, 3)), draw(st.integers(1, 3))
    counts = draw(st.lists(st.integers(0, 3), min_size=w * h, max_size=w * h))
    indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    if draw(st.booleans()):  # a broken row pointer
        indptr[draw(st.integers(0, len(indptr) - 1))] += draw(st.integers(-3, 3))
    nnz = int(sum(counts)) + draw(st.sampled_from([0, 0, 0, 1, -1]))
    nnz = max(nnz, 0)
    ids = np.asarray(draw(st.lists(st.integers(-2, n_g + 1), min_size=nnz, max_size=nnz)), np.int32)
    weights = _array(draw, (nnz,))
    order = np.asarray(draw(st.permutations(range(n_g))), np.int32)
    if draw(st.booleans()):
        order[0] = order[-1]  # not a permutation
    return n_g, w, h, indptr, ids, weights, order


@CONTENTS
@given(caches())
def test_blend_cache_reader_on_arbitrary_contents(tmp_path_factory, doc):
    import torch

    n_g, w, h, indptr, ids, weights, order = doc
    p = _path(tmp_path_factory, "cache.h5")
    with write_h5(p, "goi.blend_cache", {}) as f:
        f.attrs.update(n_gaussians=n_g, top_k=0, ply_sha256="x", cameras_sha256="y")
        put(f, "order", order)
        g = f.create_group("views").create_group("v")
        g.attrs.update(width=w, height=h, mass_kept=1.0, entries_total=len(ids))
        put(g, "indptr", indptr)
        put(g, "indices", ids)
        put(g, "weights", weights)
    try:
        cache = BlendCache.load(p)
    except GoiError:
        return
    out = FeatureRenderer.from_cache(cache).render(torch.ones(n_g, 2), np.arange(w * h))
    assert torch.isfinite(out).all()


@CONTENTS
@given(st.lists(st.integers(0, 255), min_size=1, max_size=20), st.integers(0, 25))
def test_selection_reader_on_arbitrary_contents(tmp_path_factory, values, n_selected):
    p = _path(tmp_path_factory, "sel.h5")
    with write_h5(p, "goi.selection", {}) as f:
        f.attrs.update(prompt="x", mode="hyperplane", n_gaussians=len(values),
                       n_selected=n_selected, ply_sha256="x")  # fmt: skip
        put(f, "selected", np.asarray(values, np.uint8))
    try:
        sel = load_selection(p)
    except GoiError:
        return
    assert set(np.unique(np.asarray(values))) <= {0, 1}
    assert int(sel.selected.sum()) == n_selected


def test_the_readers_refuse_what_the_properties_allow_to_pass(tmp_path):
    """Pin the one case each property would silently skip if the reader accepted everything."""
    p = tmp_path / "sel.h5"
    with write_h5(p, "goi.selection", {}) as f:
        f.attrs.update(prompt="x", mode="m", n_gaussians=3, n_selected=1, ply_sha256="x")
        put(f, "selected", np.asarray([0, 2, 0], np.uint8))
    with pytest.raises(GoiError, match="other than 0 and 1"):
        load_selection(p)
