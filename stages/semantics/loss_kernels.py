"""Row-wise kernels of the field's codebook losses: every sum the losses need from one row of a
[B, N] matrix, and that row's gradient, in one pass while the row sits in cache.

Written out with torch ops the same work is a dozen full passes over [B, N] (logsumexp,
softmax, products, sums, the gradient, two indexed updates); a row of N = 300 floats fits in
L1, so fusing them leaves the matrix products and one vectorised exp as the heavy part. The
exponentials come from torch (vectorised; numba's math.exp is not without SVML). Rows are
independent, so the result does not depend on the number of threads.
"""

from __future__ import annotations

import math

import numba


@numba.njit(parallel=True, fastmath=True, cache=True)
def shifted_rows(sim, e, tau, z, d, s_max, q, e_idx):
    """For each row, one pass over the cosines sim [B, N] and one over the decoder's logits
    e [B, N]: d [B], s_max [B] the argmax and max of sim (the first on ties, as torch's),
    z = tau (sim - s_max) [B, N]; e_idx [B] the argmax of e and q = e - max(e) [B, N].
    exp(z) and exp(q) are softmax(tau sim) and softmax(e) before their row sums (the callers
    exponentiate with torch, vectorised)."""
    b, n = sim.shape
    for i in numba.prange(b):
        row, best = sim[i], 0
        for j in range(1, n):
            if row[j] > row[best]:
                best = j
        d[i], s_max[i] = best, row[best]
        for j in range(n):
            z[i, j] = tau * (row[j] - row[best])
        row, best = e[i], 0
        for j in range(1, n):
            if row[j] > row[best]:
                best = j
        e_idx[i] = best
        for j in range(n):
            q[i, j] = row[j] - row[best]


@numba.njit(parallel=True, fastmath=True, cache=True)
def codebook_rows(sim, p, e_idx, d, tau, w_ent, w_max, w_e2e, ent):
    """For each row: sim [B, N] cosines, p [B, N] = exp(tau (sim - max)), d [B] the argmax of
    sim and e_idx [B] the entry the decoder picked. Writes ent [B], the entropy of
    softmax(tau sim), and overwrites sim with dL/dsim of the row's share of
    w_ent L_ent + w_max L_max + w_e2e L_e2e (without the 1/B of the mean):
    dH/dsim = -tau p (z - E_p[z]) for z = tau sim, and -1 at d and at e_idx."""
    b, n = sim.shape
    for i in numba.prange(b):
        row, pr = sim[i], p[i]
        total = 0.0
        ez = 0.0
        for j in range(n):
            total += pr[j]
            ez += pr[j] * row[j]
        ez *= tau / total  # E_p[z]
        ent[i] = tau * row[d[i]] + math.log(total) - ez  # logsumexp(z) - E_p[z]
        scale = -w_ent * tau / total
        for j in range(n):
            row[j] = scale * pr[j] * (tau * row[j] - ez)
        row[d[i]] -= w_max
        row[e_idx[i]] -= w_e2e


@numba.njit(parallel=True, fastmath=True, cache=True)
def joint_rows(q, d, scale, sq):
    """For each row of q = exp(e - max e) [B, N] (softmax(e) before its row sum, normalised
    here) and target entries d [B]: sq [B] the squared distance |softmax(e) - onehot(d)|^2,
    and q overwritten with d/de of scale * that distance: with r = softmax(e) - onehot(d) and
    g = 2 scale r = dL/dq, dL/de = q (g - sum(q g))."""
    b, n = q.shape
    for i in numba.prange(b):
        row = q[i]
        t = d[i]
        total = 0.0
        for j in range(n):
            total += row[j]
        inv = 1.0 / total
        for j in range(n):
            row[j] *= inv
        dist = 0.0
        qg = 0.0
        for j in range(n):
            dist += row[j] * row[j]
            qg += row[j] * row[j]
        # the target's entry: r = q - 1 there
        dist += 1.0 - 2.0 * row[t]
        qg = 2.0 * scale * (qg - row[t])
        sq[i] = dist
        q_t = row[t]
        for j in range(n):
            row[j] = row[j] * (2.0 * scale * row[j] - qg)
        row[t] = q_t * (2.0 * scale * (q_t - 1.0) - qg)
