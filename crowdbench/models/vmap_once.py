"""Parameter-free work done once, not once per parameter copy, under TorchRL's vmapped critics.

TorchRL's ``TD3Loss`` (and ``SACLoss``) evaluates ONE critic module on ``td.expand(2, B)`` under
``torch.vmap`` over its stacked parameter copies: every input of the critic is the same tensor
for both copies (a batch dimension of stride 0), yet vmap runs every op on a materialised
``[2, B, ...]`` tensor. Work that reads no parameter (the lookahead critic's predicted
observation and graph, the LSTM's sort) gives the same result for both copies, so :func:`once`
computes it plain on one copy and hands vmap the result expanded again. Measured: the lookahead
critic's graph construction was about a quarter of a gatedgcn update.

Bits: the forward values are the same (the ops act per row; both copies are identical). In the
backward, ``expand`` sums the copies' gradients *before* the preprocessing's backward instead of
after it. That is exact when at most one copy's gradient is nonzero per row, which holds for the
losses here: TorchRL's TD3 actor term reads critic 1 only (critic 2's gradient is exactly zero;
crowdbench's TD3 runs critic 1 alone there, algos/td3.py), SAC's
reads ``min(Q1, Q2)`` (one copy per row), the critic terms take no gradient of the observation
or the action (tested: ``tests/test_vmap_once.py``). Anything else (nested transforms, inputs that
differ between copies) takes the ordinary vmapped path.
"""

from __future__ import annotations

import torch
from torch._C import _functorch as _ft
from torch.utils import _pytree


def _shared_copy(t: torch.Tensor):
    """``(plain, level, n)`` if ``t`` is a BatchedTensor over a stride-0 expand of a plain tensor,
    ``(t, None, None)`` for a plain tensor, ``None`` otherwise."""
    if not _ft.is_functorch_wrapped_tensor(t):
        return t, None, None
    if not _ft.is_batchedtensor(t):
        return None
    phys = _ft.get_unwrapped(t)
    bdim = _ft.maybe_get_bdim(t)
    if _ft.is_functorch_wrapped_tensor(phys) or phys.stride(bdim) != 0:
        return None
    return phys.select(bdim, 0), _ft.maybe_get_level(t), phys.shape[bdim]


def once(fn, *args):
    """``fn(*args)`` for a parameter-free ``fn``; under vmap over copies of the same inputs, run
    once on one copy (module docstring). ``fn`` returns a tensor or a pytree of tensors."""
    plain, level, n = [], None, None
    for a in args:
        if not isinstance(a, torch.Tensor):
            plain.append(a)
            continue
        got = _shared_copy(a)
        if got is None or (got[1] is not None and level is not None and (got[1], got[2]) != (level, n)):
            return fn(*args)
        plain.append(got[0])
        if got[1] is not None:
            level, n = got[1], got[2]
    if level is None:
        return fn(*args)
    out = fn(*plain)
    return _pytree.tree_map(lambda t: _ft._add_batch_dim(t.unsqueeze(0).expand(n, *t.shape), 0, level), out)


def batch_max(n: torch.Tensor) -> int:
    """The largest entry of ``n`` over the batch and every vmapped copy (a Python int: under
    ``torch.func`` read from the underlying tensor, which holds all copies)."""
    while _ft.is_functorch_wrapped_tensor(n):
        n = _ft.get_unwrapped(n)
    return int(n.max()) if n.numel() else 0
