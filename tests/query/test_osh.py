"""The OSH's math: the per-entry loss against the paper's per-pixel loss."""

import numpy as np

from stages.query.osh import Counts, HyperplaneParams, fit_osh, loss_gradient


def test_fit_osh_per_entry_equals_the_per_pixel_loss():
    """The loss summed per codebook entry has the same gradient as the paper's per-pixel sum."""
    import torch

    rng = np.random.default_rng(0)
    n, d = 12, 8
    T = rng.normal(size=(n, d))
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    idx = rng.integers(0, n, 500)
    m = (idx < 4) ^ (rng.random(500) < 0.05)  # entries 0-3 are the target, 5% label noise
    counts = Counts(np.bincount(idx[m], minlength=n) * 1.0, np.bincount(idx[~m], minlength=n) * 1.0)
    t = T[3]
    o = HyperplaneParams()
    g = loss_gradient(counts, T @ t - o.threshold, o)  # dL/dz per entry
    W = torch.tensor(t, requires_grad=True)
    b = torch.tensor(-o.threshold, dtype=torch.float64, requires_grad=True)
    z = torch.from_numpy(T[idx]) @ W + b
    y = torch.from_numpy(m.astype(np.float64))
    loss = -(
        o.positive_weight * y * torch.nn.functional.logsigmoid(z)
        + (1 - y) * torch.nn.functional.logsigmoid(-z)
    ).mean()
    loss.backward()
    np.testing.assert_allclose(T.T @ g, W.grad.numpy(), atol=1e-12)
    np.testing.assert_allclose(g.sum(), float(b.grad), atol=1e-12)
    # and fitting from there raises the agreement with the mask
    _, _, rec = fit_osh(counts, T, t, HyperplaneParams(lr=1.0, steps=2000))
    assert rec["res_iou"] > rec["res_iou_init"] + 0.1
