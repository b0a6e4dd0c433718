"""The fused losses (hand-derived gradients) against the paper's formulation under autograd."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from stages.semantics.field_model import (
    FieldModel,
    field_losses,
    reference_field_losses,
)
from stages.semantics.field_params import FieldParams


def _model_and_batch(seed: int, b: int = 257, n: int = 23, d: int = 16, s: int = 5):
    g = torch.Generator().manual_seed(seed)
    codebook = F.normalize(torch.randn(n, d, generator=g), dim=1) * 1.7  # not unit: normalised
    model = FieldModel(40, s, codebook.numpy(), direct=False)
    with torch.no_grad():
        model.features.normal_(generator=g)
        model.decoder.weight.normal_(generator=g)
    # Targets near entries, as real features are, so that argmaxes are clear and ties absent.
    near = codebook[torch.randint(n, (b,), generator=g)]
    v_gt = F.normalize(near + 0.4 * torch.randn(b, d, generator=g), dim=1)
    rows = torch.randint(40, (b, 3), generator=g)
    return model, v_gt, rows


def _grads(fn, model, v_gt, rows, tau, p):
    model.zero_grad()
    f_hat = model.features[rows].mean(1)  # [B, S]: something differentiable to the features
    loss, parts = fn(model, f_hat, v_gt, tau, p)
    loss.backward()
    return parts, [t.grad.clone() for t in model.parameter_list()]


@pytest.mark.parametrize("tau", [1.0, 2.0])
@pytest.mark.parametrize("weights", [(0.3, 1.0, 1.0, 1.0), (1.0, 0.0, 2.0, 0.5)])
def test_fused_losses_equal_the_reference_values_and_gradients(tau, weights):
    w_ent, w_max, w_joint, w_e2e = weights
    p = FieldParams(w_ent=w_ent, w_max=w_max, w_joint=w_joint, w_e2e=w_e2e)
    model, v_gt, rows = _model_and_batch(seed=int(tau * 10) + int(w_ent * 3))
    fast, g_fast = _grads(field_losses, model, v_gt, rows, tau, p)
    ref, g_ref = _grads(reference_field_losses, model, v_gt, rows, tau, p)
    np.testing.assert_allclose(fast, ref, rtol=1e-5, atol=1e-6)
    for name, a, b in zip(("features", "weight", "bias", "codebook"), g_fast, g_ref, strict=True):
        scale = float(b.abs().max())
        assert scale > 0, name  # every parameter gets a gradient: the test can tell them apart
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5 * scale, msg=name)


def test_each_term_moves_the_gradient():
    """Dropping any one term changes the codebook's gradient: none is silently ignored."""
    model, v_gt, rows = _model_and_batch(seed=3)
    _, full = _grads(field_losses, model, v_gt, rows, 1.0, FieldParams())
    for term in ("w_ent", "w_max", "w_joint", "w_e2e"):
        _, without = _grads(field_losses, model, v_gt, rows, 1.0, FieldParams(**{term: 0.0}))
        changed = [not torch.allclose(a, b) for a, b in zip(full, without, strict=True)]
        assert any(changed), term


def test_direct_ablation_uses_the_cosine_loss():
    model = FieldModel(10, 4, np.eye(6, 8, dtype=np.float32), direct=True)
    v_gt = F.normalize(torch.randn(7, 8), dim=1)
    f_hat = torch.randn(7, 4)
    loss, parts = field_losses(model, f_hat, v_gt, 1.0, FieldParams(no_tfcc=True))
    e = model.decoder(f_hat)
    expect = 1 - (v_gt * F.normalize(e, dim=1)).sum(1).mean()
    assert float(loss.detach()) == pytest.approx(float(expect.detach())) and parts[0] == parts[4]
