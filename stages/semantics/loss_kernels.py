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
    """For each row of q = softmax(e) [B, N] and target entries d [B]: sq [B] the squared
    distance |q - onehot(d)|^2, and q overwritten with d/de of scale * that distance:
    with r = q - onehot(d) and g = 2 scale r = dL/dq, dL/de = q (g - sum(q g))."""
    b, n = q.shape
    for i in numba.prange(b):
        row = q[i]
        t = d[i]
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
