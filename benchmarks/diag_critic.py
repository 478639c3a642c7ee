"""Does the critic know which action avoids a collision? (docs/training.md, "Why the lookahead critic")

    python benchmarks/diag_critic.py RUN/checkpoint.pt

Rolls out straight-to-goal on 512 students001 training episodes and evaluates critic 1 of the
checkpoint's TD3 loss: Q(s, straight) in states 1, 2 and 4 steps before a collision against states
safe for 8+ steps (does Q know *when* a collision comes?), and the arg-max of Q(s, .) over 16
full-speed headings one step before a collision (does Q know *which action* avoids it? a share of
arg-max headings within 45 degrees of the goal close to 1 means it does not). TD3/DDPG checkpoints.
"""

from __future__ import annotations

import sys

import torch
from omegaconf import OmegaConf

from crowdbench.algos.checkpoint import load_checkpoint
from crowdbench.algos.registry import component
from crowdbench.baselines.straight import StraightToGoal
from crowdbench.envs.factory import replay_env
from crowdbench.envs.rules import COLLISION
from crowdbench.models.heads import prepare_batch

NEVER = 10**6


def main(path: str, batch: int = 512, steps: int = 30) -> None:
    torch.set_num_threads(1)
    state = load_checkpoint(path)
    cfg = OmegaConf.create(state["config"])
    loss = component(cfg.algo.name)(cfg, 1).loss
    loss.load_state_dict(state["loss"])
    params = loss.qvalue_network_params[0] if hasattr(loss, "qvalue_network_params") else loss.value_network_params
    net = loss.qvalue_network if hasattr(loss, "qvalue_network") else loss.value_network

    env = replay_env("students001", batch, seed=7)
    pol = StraightToGoal()
    td = env.reset()
    obs, first = [], torch.full((batch,), NEVER)
    for t in range(steps):
        obs.append(td.clone())
        td["agents", "action"] = pol.act(td)
        td = env.step(td)["next"]
        hit = td["agents", "info", "outcome"][:, 0] == COLLISION
        first = torch.where((first == NEVER) & hit, t, first)

    def q(tdx, action):
        tdx = tdx.clone()
        tdx["agents", "action"] = action
        prepare_batch(tdx, getattr(net.module, "head", net.module).encoder, include_next=False)
        with params.to_module(net):
            return net(tdx)["agents", "state_action_value"][:, 0, 0]

    ang = torch.linspace(0, 2 * torch.pi, 17)[:-1]
    dirs = torch.stack((ang.cos(), ang.sin()), -1)
    for lead in (1, 2, 4):
        before, safe, best = [], [], []
        for t in range(5, steps - 5):
            running = first >= t
            qs = q(obs[t], pol.act(obs[t]))
            c, s = running & (first == t + lead - 1), running & (first > t + 8)
            before.append(qs[c])
            safe.append(qs[s])
            if lead == 1 and c.any():
                n = int(c.sum())
                allq = torch.stack([q(obs[t][c], dirs[i].expand(n, 1, 2)) for i in range(16)], -1)
                best.append(dirs[allq.argmax(-1)][:, 0])
        qc, qs = torch.cat(before), torch.cat(safe)
        print(f"Q(s, straight) {lead} step(s) before a collision: {qc.mean():.3f} (n={len(qc)}); "
              f"safe for 8+ steps: {qs.mean():.3f} (n={len(qs)})")
        if best:
            b = torch.cat(best)
            print(f"  arg-max Q heading one step before a collision: within 45 deg of the goal in "
                  f"{(b > 0.7071).float().mean():.2f} of {len(b)} states")


if __name__ == "__main__":
    main(sys.argv[1])
