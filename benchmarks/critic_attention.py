"""How sharp is a critic's attention over the humans? (docs/baselines.md, "The seeds that fail")

    python benchmarks/critic_attention.py RUN/checkpoint.pt [RUN2/checkpoint.pt ...]
    python benchmarks/critic_attention.py --actor leaderboard/submissions/sarl_td3_s*/checkpoint.pt

For TD3/DDPG training checkpoints (a run's ``checkpoint.pt``) of an attention encoder (sarl, rgl,
gat, dsrnn; gatedgcn's sigmoid gates are shown the same way); ``--actor`` reads the actor's
attention instead, the only network a leaderboard submission keeps.
Straight-to-goal runs 64 students001 training episodes (seed 7) for 10 steps; on those observations
the checkpoint's actor picks its action and critic 1 reads the graph it reads in the actor loss
(the lookahead prediction under that action, when the run has one). Printed per checkpoint: the
mean entropy of the robot's attention row (nats; per head, then averaged) and its mean largest
weight, over the observations with at least 2 attended nodes, next to the entropy of a uniform row
over the same nodes. RGL's row is its adjacency row, the robot's self-weight included (the
softmax's support); the others' rows are their weights over the observed humans (GAT: over the
robot's incoming edges, goal included), renormalised to 1.
"""

from __future__ import annotations

import sys

import torch
from omegaconf import OmegaConf

from crowdbench.algos.checkpoint import load_checkpoint
from crowdbench.algos.registry import component
from crowdbench.baselines.straight import StraightToGoal
from crowdbench.envs.factory import replay_env
from crowdbench.models.heads import lookahead


def observations(batch: int = 64, steps: int = 10):
    env = replay_env("students001", batch, seed=7)
    pol, td = StraightToGoal(), env.reset()
    for _ in range(steps):
        td["agents", "action"] = pol.act(td)
        td = env.step(td)["next"]
    obs = td["agents", "observation"]
    return obs["robot"][:, 0], obs["humans"][:, 0], obs["humans_mask"][:, 0]


def attention_rows(encoder) -> tuple[torch.Tensor, torch.Tensor]:
    """``weights [B, K, C]`` (C heads or channels) and ``mask [B, K]`` of the most recent plain call."""
    gates = encoder.last_gates
    if gates is None:
        raise SystemExit(f"encoder {type(encoder).__name__} has no attention over the humans (no last_gates)")
    row = getattr(encoder, "last_adjacency", None)
    if row is None:
        return gates.full, gates.mask
    mask = torch.cat((torch.ones_like(gates.mask[:, :1]), gates.mask[:, 1:]), -1)  # robot self, humans
    return row.unsqueeze(-1), mask


def sharpness(weights: torch.Tensor, mask: torch.Tensor) -> dict[str, float]:
    w = weights.clamp_min(0) * mask.unsqueeze(-1)
    p = w / w.sum(1, keepdim=True).clamp_min(1e-12)
    ent = -(p * p.clamp_min(1e-12).log()).sum(1).mean(-1)  # [B]: per head, averaged over heads
    top = p.amax(1).mean(-1)
    n = mask.sum(-1)
    keep = n >= 2
    return {"entropy": float(ent[keep].mean()), "max_weight": float(top[keep].mean()),
            "uniform_entropy": float(n[keep].float().log().mean()), "rows": int(keep.sum())}


def measure_actor(path: str, obs) -> dict[str, float]:
    from crowdbench.algos.checkpoint import policy_from_checkpoint

    actor = policy_from_checkpoint(path).actor
    with torch.no_grad():
        actor.module(*obs)
    enc = actor.module.encoder
    return sharpness(*attention_rows(enc))


def measure(path: str, obs) -> dict[str, float]:
    state = load_checkpoint(path)
    if "loss" not in state:
        raise SystemExit(f"{path}: no critic in this checkpoint (a submission holds the actor only)")
    cfg = OmegaConf.create(state["config"])
    learner = component(cfg.algo.name)(cfg, 1)
    learner.loss.load_state_dict(state["loss"])
    net = learner.critic_network()
    params = learner.critic_params()
    params = params[0] if params.batch_size else params  # TD3's twin critics: copy 1
    robot, humans, mask = obs
    with torch.no_grad():
        action = learner.actor.module(robot, humans, mask)
        crit = net.module
        if crit.lookahead_dt > 0:
            robot, humans, mask = lookahead(robot, humans, mask, action, crit.lookahead_dt, crit.v_max)
        with params.to_module(net):
            crit.encoder(robot, humans, mask)  # the raw forward records the attention (never compacted)
    return sharpness(*attention_rows(crit.encoder))


def main(paths: list[str]) -> None:
    torch.set_num_threads(1)
    actor = "--actor" in paths
    paths = [p for p in paths if p != "--actor"]
    obs = observations()
    print(f"{'checkpoint (' + ('actor' if actor else 'critic 1') + ')':60s} {'entropy':>8s} {'max w':>6s} "
          f"{'uniform':>8s} {'rows':>5s}")
    for path in paths:
        r = measure_actor(path, obs) if actor else measure(path, obs)
        print(f"{path:60s} {r['entropy']:8.2f} {r['max_weight']:6.2f} {r['uniform_entropy']:8.2f} {r['rows']:5d}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    main(sys.argv[1:])
