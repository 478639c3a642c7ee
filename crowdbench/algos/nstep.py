"""n-step returns on a collected ``[B, T]`` batch, per agent, before it enters the replay buffer.

Each transition ``t`` of an agent becomes ``(s_t, a_t, R, s_{t+m})`` with
``R = sum_{k<m} gamma^k r_{t+k}``, ``m = min(n, steps to the agent's episode end, steps left
in the batch)``, the ``done``/``terminated`` flags of step ``t+m-1`` and ``steps_to_next_obs = m``,
which TorchRL's TD(0) estimator turns into the bootstrap discount ``gamma^m``.

Why not TorchRL's ``MultiStep`` postproc: in torchrl 0.14 it shifts the next observation to
the terminal step but keeps the *first* step's done flags, so a transition that ends its
episode within ``n`` steps bootstraps from the terminal state (checked: ``MultiStep(0.5, 3)``
on a 6-step episode gives ``terminated=False`` with the terminal observation for step 3); it
also expects one root-level reward/done key, while ours are per agent (``[B, T, A, 1]``).
The loop below runs over the ``n`` offsets only (n <= ~10), never over environments or agents.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from crowdbench.envs.observation import GROUP

STEPS = (GROUP, "steps_to_next_obs")  # the value estimator reads this key (algos/offpolicy.py)


def n_step(batch: TensorDictBase, n: int, gamma: float) -> TensorDictBase:
    """Return a copy of ``batch`` ``[B, T]`` whose per-agent transitions are n-step (see module doc)."""
    if n < 1:
        raise ValueError(f"algo.n_steps must be >= 1, got {n}")
    nxt = batch["next", GROUP]
    reward, done = nxt["reward"], nxt["done"]  # [B, T, A, 1]
    T = batch.batch_size[1]
    t = torch.arange(T)
    ret = torch.zeros_like(reward)
    last = torch.zeros(batch.batch_size[0], T, *done.shape[2:], dtype=torch.long)  # offset of the final step
    alive = torch.ones_like(done)  # no episode end between t and t+k-1
    for k in range(min(n, T)):
        idx = (t + k).clamp(max=T - 1)
        valid = alive & (t + k < T).view(1, T, 1, 1)
        ret = ret + valid * gamma**k * reward[:, idx]
        last = torch.where(valid, k, last)
        alive = valid & ~done[:, idx]
    gather = (t.view(1, T, 1, 1) + last)  # [B, T, A, 1] step whose next observation ends the transition
    out = batch.clone(False)
    shifted = nxt.exclude("reward").apply(lambda x: x.gather(1, gather.view(*gather.shape[:3], *[1] * (x.dim() - 3))
                                                              .expand(*gather.shape[:3], *x.shape[3:])))
    shifted.set("reward", ret)
    out.set(("next", GROUP), shifted)
    out.set(STEPS, last + 1)
    return out
