"""The semantic field's model and losses (paper section 3.4 and appendix; the hyperparameters
are `field_params.FieldParams`).

Per Gaussian a low-dimensional feature f (zero at start), rendered by alpha blending to f_hat; a
linear decoder D: S -> N gives logits e; the decoded feature is T[argmax e] with T the codebook.
Losses (weights and schedule as the authors' code):
  L_ent   = entropy(softmax(tau cos(v_gt, T)))            x 0.3, tau 1 -> 2 after 2/3 of the run
  L_max   = 1 - cos(v_gt, T[d]), d = argmax cos(v_gt, T)   x 1
  L_joint = 50 MSE(softmax(e), onehot(d))                 x 1 (the authors' form of |e - 1_d|^2)
  L_e2e   = 1 - cos(v_gt, T[argmax e])                     x 1 (reaches the codebook only)
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from stages.semantics.field_params import FieldParams
from stages.semantics.loss_kernels import codebook_rows, joint_rows, shifted_rows

#: Names of the loss curve's columns, in order.
LOSS_NAMES = ("total", "ent", "max", "joint", "e2e")


class FieldModel(torch.nn.Module):
    """The trainable parts: per-Gaussian features [G, S], the decoder S -> N (direct: S -> D)
    and the codebook [N, D].

    With `order` (the blend cache's column order: row j is Gaussian order[j]) the features are
    held in that order while fitting; `ply_rows` / `model_rows` convert a [G, ...] array, so
    that every artifact stays in PLY order."""

    def __init__(
        self,
        n_gaussians: int,
        sem_dim: int,
        codebook: np.ndarray,
        direct: bool,
        order: np.ndarray | None = None,
    ):
        super().__init__()
        self.features = torch.nn.Parameter(torch.zeros(n_gaussians, sem_dim))
        self.decoder = torch.nn.Linear(sem_dim, codebook.shape[1 if direct else 0])
        self.codebook = torch.nn.Parameter(torch.from_numpy(codebook.copy()))
        self.order = order

    def parameter_list(self) -> list[torch.Tensor]:
        """In the order of `PARAMETERS`."""
        return [self.features, self.decoder.weight, self.decoder.bias, self.codebook]

    def ply_rows(self, a: np.ndarray) -> np.ndarray:
        """A per-Gaussian array [G, ...] held in the model's row order, in PLY order."""
        if self.order is None:
            return a
        out = np.empty_like(a)
        out[self.order] = a
        return out

    def model_rows(self, a: np.ndarray) -> np.ndarray:
        """The inverse of `ply_rows`."""
        return a if self.order is None else a[self.order]

    def arrays(self) -> dict[str, np.ndarray]:
        """The parameters by their `PARAMETERS` names, features in PLY order."""
        tensors = zip(PARAMETERS, self.parameter_list(), strict=True)
        out = {name: t.detach().numpy() for name, t in tensors}
        out["features"] = self.ply_rows(out["features"])
        return out


#: The model's tensors as the field and checkpoint artifacts name them.
PARAMETERS = ("features", "decoder_weight", "decoder_bias", "codebook")


def field_losses(
    model: FieldModel, f_hat: torch.Tensor, v_gt: torch.Tensor, tau: float, p: FieldParams
) -> tuple[torch.Tensor, list[float]]:
    """The weighted total and each term (LOSS_NAMES) for rendered features f_hat [B, S] and
    unit target features v_gt [B, D]: the same values and gradients as
    `reference_field_losses`, from one cosine matrix and hand-derived gradients
    (`_CodebookLosses`, `_JointLoss`): the autograd graph of the plain formulation spends most
    of a step in a dozen elementwise passes over [B, N] and in the indexed accumulation of
    T[argmax e]'s gradient. `p.reference_losses` (and the direct ablation) take the plain one."""
    if p.no_tfcc or p.reference_losses:
        return reference_field_losses(model, f_hat, v_gt, tau, p)
    e = model.decoder(f_hat)  # [B, N]
    t_unit = F.normalize(model.codebook, dim=1)  # [N, D]
    weights = (p.w_ent, p.w_max, p.w_e2e)
    sim = v_gt @ t_unit.detach().T  # [B, N] cosines
    b, n = sim.shape
    z, q = torch.empty_like(sim), torch.empty(b, n)  # [B, N] each, exponentiated below
    d, e_idx = np.empty(b, np.int64), np.empty(b, np.int64)
    s_max = np.empty(b, np.float32)
    shifted_rows(sim.numpy(), e.detach().numpy(), tau, z.numpy(), d, s_max, q.numpy(), e_idx)
    codebook_part, terms = _CodebookLosses.apply(
        t_unit, v_gt, sim, z.exp_(), e_idx, d, s_max, tau, weights
    )
    l_joint = _JointLoss.apply(e, q.exp_(), d)
    total = codebook_part + p.w_joint * l_joint
    ent, mx, e2e = (float(x) for x in terms)
    return total, [float(total.detach()), ent, mx, float(l_joint.detach()), e2e]


class _CodebookLosses(torch.autograd.Function):
    """w_ent L_ent + w_max L_max + w_e2e L_e2e, all three read off sim = v_gt T_unit^T [B, N]:
    L_max and L_e2e are single entries of it (v_gt and T_unit are unit vectors, so the cosine
    with T[d] is sim[:, d]). With z = tau sim and p = softmax(z), the entropy's gradient is
    dH/dz = -p (z - E_p[z]); the other two add -1/B at one entry per row (`codebook_rows`
    does a row in one pass). The backward is then one [N, B] x [B, D] product."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx,
        t_unit: torch.Tensor,  # [N, D]
        v_gt: torch.Tensor,  # [B, D] unit
        sim: torch.Tensor,  # [B, N] v_gt t_unit^T, overwritten with dL/dsim
        p: torch.Tensor,  # [B, N] exp(tau (sim - s_max)): softmax(tau sim) unnormalised
        e_idx: np.ndarray,  # [B] argmax of the decoder's logits
        d: np.ndarray,  # [B] argmax of sim
        s_max: np.ndarray,  # [B] max of sim
        tau: float,
        weights: tuple[float, float, float],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        b = v_gt.shape[0]
        rows = np.arange(b)
        s_e2e = sim.numpy()[rows, e_idx].astype(np.float64)
        ent = np.empty(b, np.float64)
        codebook_rows(sim.numpy(), p.numpy(), e_idx, d, tau, *weights, ent)
        terms = torch.tensor(
            [ent.mean(), 1 - float(s_max.astype(np.float64).mean()), 1 - float(s_e2e.mean())],
            dtype=sim.dtype,
        )
        total = (torch.tensor(weights, dtype=sim.dtype) * terms).sum()
        ctx.mark_non_differentiable(terms)
        ctx.save_for_backward(sim, v_gt)
        ctx.set_materialize_grads(False)
        return total, terms

    @staticmethod
    def backward(ctx, g_total, _g_terms):  # type: ignore[override]  # noqa: ANN001, ANN205
        grad, v_gt = ctx.saved_tensors  # grad: dL/dsim without the mean's 1/B
        grad_t = grad.T @ v_gt * (g_total / grad.shape[0])  # [N, D]
        return grad_t, None, None, None, None, None, None, None, None


class _JointLoss(torch.autograd.Function):
    """L_joint = 50 mean((softmax(e) - onehot(d))^2) with its gradient through the softmax,
    dL/de = q (g - sum(q g)) for q = softmax(e) and g = dL/dq (`joint_rows`: a row a pass)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx,
        e: torch.Tensor,  # [B, N] decoder logits
        q: torch.Tensor,  # [B, N] exp(e - max e), overwritten with dL/de
        d: np.ndarray,  # [B] the target entries
    ) -> torch.Tensor:
        b, n = e.shape
        scale = 50.0 / (b * n)  # the mean over B N
        sq = np.empty(b, np.float64)
        joint_rows(q.numpy(), d, scale, sq)
        ctx.save_for_backward(q)
        return torch.tensor(scale * sq.sum(), dtype=e.dtype)

    @staticmethod
    def backward(ctx, g_loss):  # type: ignore[override]  # noqa: ANN001, ANN205
        (grad,) = ctx.saved_tensors
        return grad.mul_(g_loss), None, None  # the graph is used once: no need to keep grad


def reference_field_losses(
    model: FieldModel, f_hat: torch.Tensor, v_gt: torch.Tensor, tau: float, p: FieldParams
) -> tuple[torch.Tensor, list[float]]:
    """The losses written as the paper states them, differentiated by autograd: the plain twin
    of `field_losses` (tests hold the two equal) and the path of the direct ablation."""
    e = model.decoder(f_hat)  # [B, N] (direct: [B, D])
    if p.no_tfcc:
        loss = 1 - (v_gt * F.normalize(e, dim=1)).sum(1).mean()
        return loss, [float(loss.detach()), 0.0, 0.0, 0.0, float(loss.detach())]
    t_unit = F.normalize(model.codebook, dim=1)  # [N, D]
    sim = v_gt @ t_unit.T  # [B, N] cosines (v_gt is unit)
    prob = torch.softmax(sim * tau, dim=1)
    l_ent = -(prob * torch.log(prob.clamp_min(1e-12))).sum(1).mean()
    s_max, d = sim.max(dim=1)
    l_max = 1 - s_max.mean()
    l_joint = 50 * F.mse_loss(torch.softmax(e, dim=1), F.one_hot(d, sim.shape[1]).float())
    v = t_unit[e.argmax(dim=1)]
    l_e2e = 1 - (v_gt * v).sum(1).mean()
    total = p.w_ent * l_ent + p.w_max * l_max + p.w_joint * l_joint + p.w_e2e * l_e2e
    return total, [float(x.detach()) for x in (total, l_ent, l_max, l_joint, l_e2e)]
