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


def test_decode_kernel_keeps_the_first_of_equal_maxima():
    rng = np.random.default_rng(3)
    f = rng.normal(size=(500, 4)).astype(np.float32)
    for n in (1, 5, 8, 13, 40):
        w = rng.normal(size=(n, 4)).astype(np.float32)
        b = rng.normal(size=n).astype(np.float32)
        b[0] = b.max() + 1.0  # entry 0 wins often ...
        w[n // 2], b[n // 2] = w[0], b[0]  # ... and entry n // 2 always ties with it
        out = np.empty(500, np.int32)
        _decode_kernel(f, np.ascontiguousarray(w.T), b, out)
        logits = np.repeat(b[None], 500, axis=0)  # float32, summed in the kernel's order
        for j in range(4):
            logits += f[:, j : j + 1] * w[:, j][None]
        np.testing.assert_array_equal(out, np.argmax(logits, axis=1))  # argmax: the first
        if n > 1:
            assert np.any(out == 0) and not np.any(out == n // 2)
