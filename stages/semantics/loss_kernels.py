"""Row-wise kernels of the field's codebook losses: every quantity the losses need from one row
of a [B, N] matrix, and that row's gradient, in one pass while the row sits in cache.

Written out with torch ops the same work is a dozen full passes over [B, N] (max, argmax,
logsumexp, softmax, products, sums, the gradient, two indexed updates); a row of N = 300
floats fits in L1, so fusing them leaves the two matrix products as the only heavy part.
Rows are independent and each is summed in a fixed order, so the result does not depend on
the number of threads.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: Rows per task of the parallel loop: each task allocates its exp buffer once.
_CHUNK = 256


@numba.njit(parallel=True, cache=True)
def codebook_rows(sim, e_idx, tau, w_ent, w_max, w_e2e, ent, s_max, s_e2e, d):
    """For each row of cosines sim [B, N] (overwritten with dL/dsim of the row's share of
    w_ent L_ent + w_max L_max + w_e2e L_e2e, without the 1/B of the mean):
    ent [B] the entropy of softmax(tau sim), s_max [B] and d [B] the max and argmax,
    s_e2e [B] the cosine with the entry e_idx [B] the decoder picked."""
    b, n = sim.shape
    for c in numba.prange((b + _CHUNK - 1) // _CHUNK):
        p = np.empty(n, np.float64)
        for i in range(c * _CHUNK, min(b, (c + 1) * _CHUNK)):
            row = sim[i]
            best, arg = row[0], 0
            for j in range(1, n):
                if row[j] > best:
                    best, arg = row[j], j
            s_max[i], d[i] = best, arg
            s_e2e[i] = row[e_idx[i]]
            total = 0.0
            for j in range(n):
                p[j] = math.exp(tau * (row[j] - best))
                total += p[j]
            ez = 0.0  # E_p[z] with z = tau sim
            for j in range(n):
                p[j] /= total
                ez += p[j] * tau * row[j]
            ent[i] = tau * best + math.log(total) - ez  # logsumexp(z) - E_p[z]
            # dH/dsim = tau dH/dz = -tau p (z - E_p[z])
            for j in range(n):
                row[j] = -w_ent * tau * p[j] * (tau * row[j] - ez)
            row[arg] -= w_max
            row[e_idx[i]] -= w_e2e


@numba.njit(parallel=True, cache=True)
def joint_rows(e, d, scale, sq):
    """For each row of decoder logits e [B, N] (overwritten with d/de of
    scale * |softmax(e) - onehot(d)|^2): sq [B] that squared distance."""
    b, n = e.shape
    for c in numba.prange((b + _CHUNK - 1) // _CHUNK):
        q = np.empty(n, np.float64)
        for i in range(c * _CHUNK, min(b, (c + 1) * _CHUNK)):
            row = e[i]
            best = row[0]
            for j in range(1, n):
                best = max(best, row[j])
            total = 0.0
            for j in range(n):
                q[j] = math.exp(row[j] - best)
                total += q[j]
            # r = q - onehot(d); dL/dq = 2 scale r; dL/de = q (dL/dq - sum(q dL/dq))
            dist = 0.0
            qg = 0.0
            for j in range(n):
                q[j] /= total
                r = q[j] - 1.0 if j == d[i] else q[j]
                dist += r * r
                qg += q[j] * 2.0 * scale * r
            sq[i] = dist
            for j in range(n):
                r = q[j] - 1.0 if j == d[i] else q[j]
                row[j] = q[j] * (2.0 * scale * r - qg)
