"""MKL's VML picks each function's kernel on its first call; settled in one thread first, a
parallel first call is as accurate as every later one (stages/core/torch_numerics.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from stages.core.torch_numerics import VML_FUNCTIONS, settle_vml
from stages.semantics.fit_field import deterministic
from stages.semantics.kmeans import spherical_kmeans

#: A fresh process as goi's fit is one: numba's threads have run (the rasteriser, the blend
#: cache), then torch's first exp over many elements, on two threads. Without `settle_vml`
#: one process in three computed one thread's half of it with a low-accuracy kernel
#: (relative error 1.5e-4; 11 of 30 runs on the 2-core dev machine).
FIRST_EXP = """
import numba, numpy as np, torch
from stages.core.torch_numerics import settle_vml

@numba.njit(parallel=True)
def bump(a):
    for i in numba.prange(a.shape[0]):
        a[i] += 1.0

bump(np.zeros(100_000))
settle_vml()
torch.set_num_threads(2)
x = np.linspace(-20, 0, 2_000_000).astype(np.float32)
y = torch.exp(torch.from_numpy(x)).numpy()
e = np.exp(x.astype(np.float64))
print(float((np.abs(y - e) / e).max()))
"""


def test_every_vml_function_is_a_torch_function_and_settles():
    settle_vml.cache_clear()
    settle_vml()
    for name in VML_FUNCTIONS:
        x = torch.linspace(0.1, 0.9, 5, dtype=torch.float64)
        got = getattr(torch, name)(x).numpy()
        assert np.isfinite(got).all(), name


def test_the_fit_and_the_codebook_settle_the_choice_before_their_first_parallel_call():
    settle_vml.cache_clear()
    settled = []
    deterministic(lambda: settled.append(settle_vml.cache_info().currsize) or Path())()
    assert settled == [1]
    settle_vml.cache_clear()
    x = np.eye(4, dtype=np.float32)
    spherical_kmeans(x, 2, 1, seed=0)
    assert settle_vml.cache_info().currsize == 1


@pytest.mark.slow
def test_a_fresh_process_first_parallel_exp_is_accurate():
    # The race happens only in a fresh process, so each trial is one; 12 trials without the
    # settling would all pass with probability ~0.4 %.
    worst = []
    for _ in range(12):
        out = subprocess.run(
            [sys.executable, "-c", FIRST_EXP], capture_output=True, text=True, check=True
        )
        worst.append(float(out.stdout.strip()))
    assert max(worst) < 1e-6, worst
