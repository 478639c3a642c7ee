"""Self-play's all-pairs tests run over blocks of agents (``World._blocks``, memory linear in the number of
agents): every value must be the same bits as the all-pairs computation, kept here as the reference."""

from __future__ import annotations

import pytest
import torch

import crowdbench.envs.world as world_mod
from crowdbench.envs.factory import selfplay_world
from crowdbench.envs.rules import _FAR, RUNNING, StepInfo, outcome_of, segment_min_distance, step_reward
from crowdbench.envs.selfplay import SelfPlayConfig
from crowdbench.kinematics import advance, to_local, to_world

FRAMES = ("rotate", "translate", "world")


# ---------------------------------------------------------------------- the all-pairs reference
def ref_observe(w, frame: str, rows=None) -> dict:
    """Every agent's view from all ``[B, A, S]`` pairs at once, then its ``obs_slots`` nearest."""
    A, S = w.A, w.M_all
    pick = (lambda x: x) if rows is None else (lambda x: x[rows])
    opos, ovel, ovalid = (pick(x) for x in w.humans())
    pos, vel, goal, heading = pick(w.pos), pick(w.vel), pick(w.goal), pick(w.heading)
    B = pos.shape[0]
    opos, ovel = torch.cat((pos, opos), 1), torch.cat((vel, ovel), 1)
    ovalid = torch.cat((pick(w.present()), ovalid), 1)
    rel = opos.unsqueeze(1) - pos.unsqueeze(2)
    seen = ovalid.unsqueeze(1) & ((rel * rel).sum(-1) <= w.cfg.sensing_range**2)
    seen[:, :, :A] &= ~torch.eye(A, dtype=torch.bool)
    if frame == "world":
        rel = opos.unsqueeze(1).expand(B, A, S, 2)
    hvel = ovel.unsqueeze(1).expand(B, A, S, 2)
    own = torch.stack((vel, goal - pos if frame != "world" else goal), -2)
    if frame == "rotate":
        rel, hvel, own = to_local(rel, heading), to_local(hvel, heading), to_local(own, heading)
    humans = torch.cat((rel, hvel), -1) * seen.unsqueeze(-1)
    origin = pos if frame == "world" else torch.zeros_like(pos)
    robot = torch.cat((origin, own.reshape(B, A, 4)), -1)
    if w.M < w.M_all:
        near = rel if frame != "world" else rel - pos.unsqueeze(2)
        d2 = (near * near).sum(-1).masked_fill(~seen, float("inf"))
        idx = d2.topk(w.M, dim=-1, largest=False, sorted=True).indices
        keep = seen.gather(-1, idx)
        humans, seen = humans.gather(-2, idx.unsqueeze(-1).expand(*idx.shape, 4)) * keep.unsqueeze(-1), keep
    return {"robot": robot, "humans": humans, "humans_mask": seen}


def ref_agent_clearance(w) -> torch.Tensor:
    gap = (w.pos.unsqueeze(1) - w.pos.unsqueeze(2)).norm(dim=-1) - w.r_aa
    return gap.masked_fill(~(w.present().unsqueeze(1) & ~w.eye), _FAR)


def ref_min_clearance(w) -> torch.Tensor:
    hpos, _, hvalid = w.humans()
    gap = (hpos.unsqueeze(1) - w.pos.unsqueeze(2)).norm(dim=-1) - w.radius_sum
    gap = gap.masked_fill(~hvalid.unsqueeze(1), _FAR)
    gap = torch.cat((ref_agent_clearance(w), gap), -1)
    return gap.amin(-1)


def ref_pairs(w, new_pos, active, far):
    """The agent-agent tests of a step on all ``[B, A, A]`` pairs."""
    pair = w.present().unsqueeze(1) & ~w.eye & active.unsqueeze(-1)
    rel0 = w.pos.unsqueeze(1) - w.pos.unsqueeze(2)
    rel1 = new_pos.unsqueeze(1) - new_pos.unsqueeze(2)
    swept_aa = (segment_min_distance(rel0, rel1) - w.r_aa).masked_fill(~pair, _FAR)
    end_aa = (rel1.norm(dim=-1) - w.r_aa).masked_fill(~pair, _FAR)
    pair_hit = swept_aa < 0
    pair_hit = pair_hit | pair_hit.transpose(1, 2) & active.unsqueeze(-1)
    agent_end = end_aa.amin(-1) if w.A > 1 else far
    swept_a = swept_aa.amin(-1) if w.A > 1 else agent_end
    return pair_hit, agent_end, swept_a


def ref_step(w, action: torch.Tensor) -> StepInfo:
    """``World.step`` of a self-play world with every pair's gap tensor built at once."""
    cfg = w.cfg
    act = to_world(action.unsqueeze(-2), w.heading).squeeze(-2) if cfg.frame == "rotate" else action
    active = w.outcome == RUNNING
    vel = w.clip_action(act) * active.unsqueeze(-1)
    new_pos = advance(w.pos, vel, cfg.dt)
    env_active = active.any(-1)
    h0, h1, hv1 = w.crowd.advance(env_active, w.agents())
    gone = ~hv1.unsqueeze(1)
    p0, p1 = w.pos.unsqueeze(2), new_pos.unsqueeze(2)
    swept_h = segment_min_distance(h0.unsqueeze(1) - p0, h1.unsqueeze(1) - p1) - w.radius_sum
    swept_h = swept_h.masked_fill(gone, _FAR)
    end_h = ((h1.unsqueeze(1) - p1).norm(dim=-1) - w.radius_sum).masked_fill(gone, _FAR)
    far = torch.full((w.B, w.A), _FAR)
    swept_h = swept_h.amin(-1) if w.Mh else far
    end_h = end_h.amin(-1) if w.Mh else far
    pair_hit, agent_end, swept_a = ref_pairs(w, new_pos, active, far)
    end, swept = torch.minimum(agent_end, end_h), torch.minimum(swept_a, swept_h)
    hit = pair_hit.any(-1) | (swept_h < 0)
    steps = w.steps + env_active.long()
    collision = active & hit
    success = active & ~collision & ((w.goal - new_pos).norm(dim=-1) < cfg.robot_radius)
    timeout = active & ~collision & ~success & (steps >= cfg.time_limit).unsqueeze(-1)
    reward = step_reward(cfg, end, swept, success, collision, timeout, active)
    outcome = outcome_of(success, collision, timeout)
    w.outcome = torch.where(active, outcome, w.outcome)
    w.pos, w.vel, w.steps = new_pos, vel, steps
    w._update_heading()
    extra = {"human_clearance": end_h, "pair_collision": pair_hit, "agent_clearance": agent_end}
    return StepInfo(reward=reward, terminated=success | collision, truncated=timeout, outcome=outcome,
                    clearance=end, swept_clearance=swept, active=active, extra=extra)


# ---------------------------------------------------------------------- configurations
def on_grid(B: int, n: int, gen: torch.Generator):
    """Starts on a 0.5 m grid (many exactly tied distances), every goal 10 m along +x (axis-aligned headings
    keep the ties in the rotated frame), the agents in a random order per environment."""
    side = int(n**0.5) + 1
    axis = torch.arange(side)
    cell = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)[:n]
    order = torch.rand(B, n, generator=gen).argsort(-1)
    start = 0.5 * cell[order].float()
    return start, start + torch.tensor([10.0, 0.0])


def crowded(B: int, n: int, gen: torch.Generator):
    """Uniform starts and goals in a square holding about one agent per 0.6 m^2: collisions within steps."""
    half = 0.4 * n**0.5
    start = (2 * torch.rand(B, n, 2, generator=gen) - 1) * half
    return start, (2 * torch.rand(B, n, 2, generator=gen) - 1) * half


def twin_worlds(cfg: SelfPlayConfig, B: int, layout, seed: int):
    """Two identical worlds reset to the same episodes (``layout``'s starts and goals)."""
    gen = torch.Generator().manual_seed(seed)
    (new, scenario), (ref, _) = selfplay_world(cfg, B), selfplay_world(cfg, B)
    episode = scenario.sampler(seed)(B)  # humans' starts and goals, background start times
    if layout is not None:
        episode["start"], episode["goal"] = (x + scenario.centre for x in layout(B, cfg.n_agents, gen))
    for w in (new, ref):
        w.reset(torch.ones(B, dtype=torch.bool), episode)
    return new, ref, gen


def same(a, b, what: str) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys(), what
        for k in a:
            same(a[k], b[k], f"{what}[{k}]")
        return
    assert a.dtype == b.dtype and torch.equal(a, b), what
    if a.is_floating_point():  # torch.equal takes -0.0 for 0.0: the signs too
        assert torch.equal(a.signbit(), b.signbit()), what


def check_views(new, ref, step: int) -> None:
    for frame in FRAMES:
        same(new.observe(frame), ref_observe(ref, frame), f"step {step} observe({frame})")
    rows = torch.tensor([new.B - 1, 0])
    same(new.observe(rows=rows), ref_observe(ref, new.cfg.frame, rows), f"step {step} observe(rows)")
    same(new.min_clearance(), ref_min_clearance(ref), f"step {step} min_clearance")
    same(new.nearest_agent(), ref_agent_clearance(ref).amin(-1), f"step {step} nearest_agent")


CASES = [  # n agents, B, PAIRS (pairs a block: one agent, uneven blocks, one block), settings
    (1, 3, 1, {}),
    (2, 3, 1, {"obs_slots": 1}),
    (5, 3, 30, {"obs_slots": 2, "done_agents": "obstacle"}),  # blocks of 2, 2, 1 agents
    (13, 3, 120, {"obs_slots": 4, "frame": "translate"}),  # 3, 3, 3, 3, 1
    (13, 3, 120, {"obs_slots": 4, "frame": "world", "done_agents": "obstacle"}),
    (13, 3, 120, {"obs_slots": 30}),  # more slots than bodies: every slot
    (9, 3, 75, {"obs_slots": 5, "n_humans": 4}),  # reactive (ORCA) humans: agent-human pairs in blocks too
    (9, 3, 75, {"obs_slots": 0, "n_humans": 4, "humans": "sfm", "done_agents": "obstacle"}),
    (6, 3, 50, {"obs_slots": 8, "background": "students001"}),  # replayed humans, some absent (padding)
    (70, 16, world_mod.PAIRS, {"obs_slots": 16}),  # the default blocks: 58 + 12 agents
]


@pytest.mark.parametrize("layout", [on_grid, crowded, None], ids=["grid", "crowded", "scenario"])
@pytest.mark.parametrize(("n", "B", "pairs", "settings"), CASES)
def test_blocks_are_the_all_pairs_bits(n, B, pairs, settings, layout, monkeypatch):
    """Observations, clearances and steps (rewards, outcomes, collisions, pair_collision) equal the all-pairs
    reference bit for bit, over 12 steps of random actions in which agents collide, time out and finish."""
    monkeypatch.setattr(world_mod, "PAIRS", pairs)
    cfg = SelfPlayConfig(n_agents=n, circle_radius=max(4.0, n / 8), sensing_range=2.0, time_limit=9,
                         **{"scenario": "square", "scale_geometry": True, **settings})
    new, ref, gen = twin_worlds(cfg, B, layout, seed=n)
    for step in range(12):
        check_views(new, ref, step)
        action = 1.2 * (2 * torch.rand(B, n, 2, generator=gen) - 1)
        action[:, ::3] = 0.0  # some agents stand still (on the grid: ties stay ties)
        same(vars(new.step(action)), vars(ref_step(ref, action)), f"step {step}")
        same(new.outcome, ref.outcome, f"step {step} outcome")
    check_views(new, ref, 12)
    assert (new.outcome != RUNNING).any()  # finished agents were part of the comparison


@pytest.mark.parametrize(("n", "size"), [(32, 32), (64, 16), (128, 8), (256, 4)])
def test_blocks_hold_65536_pairs(n, size):
    """B = 64 (the scale benchmark's): 1024 pairs per environment, one block up to 32 agents."""
    world, _ = selfplay_world(SelfPlayConfig(n_agents=n, circle_radius=n / 8, obs_slots=16), 64)
    sizes = []

    def rows(r: slice):
        sizes.append(len(range(n)[r]))
        return (torch.zeros(64, sizes[-1]),)

    assert world._blocks(world.A, rows)[0].shape == (64, n)
    assert sizes == [size] * (n // size)
