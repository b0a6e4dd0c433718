"""torch's CPU numerics that "same inputs and seed give the same artifacts" depends on.

torch runs a contiguous float tensor's exp, log, sqrt, tanh, ... through MKL's VML, each
intra-op thread on its chunk. The oneMKL that torch 2.13's CPU wheels carry (2024.2) picks each
VML function's kernel lazily, on its first call, and when that first call comes from several
threads at once, one thread can run a low-accuracy kernel on its whole chunk of that call
(relative error up to 1.5e-4 instead of 1e-7; pytorch/pytorch#188792). In `goi fit-field` that
call was the first step's exp of the softmax: in 4 of 39 fresh processes one thread's half of
the exponentials came out wrong, the first step's gradient with them, and the field drifted
from there (2 of 8 demos ended with other one-view answers: the sofa 0.727 and 0.768 against
0.753). One single-threaded call of each function, in each precision, before any parallel one
settles the choice.
"""

from __future__ import annotations

import functools

#: The torch functions ATen hands to MKL's VML (`aten/src/ATen/cpu/vml.h`; abs, expm1 and log1p
#: in earlier torch versions). Each is settled: settling one does not settle another.
VML_FUNCTIONS = (
    "abs",
    "acos",
    "asin",
    "atan",
    "cos",
    "erf",
    "erfc",
    "erfinv",
    "exp",
    "expm1",
    "log",
    "log10",
    "log1p",
    "log2",
    "sin",
    "sqrt",
    "tan",
    "tanh",
    "trunc",
)


@functools.cache
def settle_vml() -> None:
    """Call each VML function once on one element, float and double, in this thread: later
    calls from many threads at once then run the accurate kernel every time. Once a process
    (the cache)."""
    import torch

    for dtype in (torch.float32, torch.float64):
        x = torch.full((1,), 0.5, dtype=dtype)
        for name in VML_FUNCTIONS:
            getattr(torch, name)(x)
