"""The numba decode kernel against its float64 reference."""

import numpy as np

from stages.semantics.decode import _decode_kernel, decode_reference


def test_decode_kernel_equals_the_reference():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(5000, 10)).astype(np.float32)
    w = rng.normal(size=(300, 10)).astype(np.float32)
    b = rng.normal(size=300).astype(np.float32)
    out = np.empty(5000, np.int32)
    _decode_kernel(f, np.ascontiguousarray(w.T), b, out)
    ref = decode_reference(f, w, b)
    logits = f.astype(np.float64) @ w.T.astype(np.float64) + b
    differ = out != ref
    # float32 vs float64 can only disagree on near-ties
    rows = np.nonzero(differ)[0]
    assert differ.mean() < 1e-3
    np.testing.assert_allclose(logits[rows, out[rows]], logits[rows, ref[rows]], atol=1e-4)
