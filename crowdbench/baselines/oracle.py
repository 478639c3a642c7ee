"""The oracle: a PRIVILEGED planner that knows every replayed human's future.

Replay is deterministic (humans never react to the robot), so the scene tensors give every
human's position at every grid step. Before the first step of an evaluation batch the oracle
plans all episodes at once with a **space-time beam search** over a discrete set of robot
velocities, using the simulator's own motion model and swept collision test
(:class:`~crowdbench.envs.world.World` ``clip_action`` and
:func:`~crowdbench.envs.rules.segment_min_distance`), then replays its plan through the normal
:class:`~crowdbench.envs.observation.Policy` interface. The simulator and the metrics code are the
same as for every other policy, so its numbers are directly comparable — but it is an upper
bound, not a policy a robot could run: **label it privileged wherever it is shown**.

Search (all episodes of a scene batched, no Python loop over episodes):

- state = robot position at a step (the robot is holonomic and its velocity may change
  arbitrarily from one step to the next, so position and time are the whole state);
- actions = ``headings`` directions (rotations of the direction to the goal, so "straight to
  the goal" is always one of them) x ``speeds`` (fractions of ``v_max``), plus stop and a
  "land on the goal" action (straight to the goal at ``min(v_max, dist/dt)``);
- a candidate whose step collides (swept test, ``d < 0`` at any moment of the step) is dropped;
  one that ends within the goal radius is a finished plan;
- cost = steps taken + ``danger_cost`` x danger steps (``0 <= d < 0.2`` at the end of a step,
  exactly the Table V metric); ranking key ``f`` = cost + remaining distance / (v_max dt)
  (a lower bound of the remaining steps);
- per episode, candidates are de-duplicated on a ``cell``-metre grid of end positions (the
  cheapest one per cell is kept) and the ``beam`` cheapest survive to the next step; the
  search stops for an episode once no surviving beam can beat its best finished plan.

Exactness: for every beam only the humans that could reach it within the step are tested
(the K nearest, with K chosen per step so that no human outside them can come within the
danger distance); this prunes work but never changes an outcome. A plan that succeeds in the
search therefore succeeds in the simulator (tests check that executed outcomes equal planned
ones). The search is not exhaustive (finite actions, finite beam), so an episode the oracle
fails is a *candidate* unavoidable collision, not a proof.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict

from crowdbench.baselines.params import ORACLE_SPEEDS, OracleSettings
from crowdbench.envs.observation import OBS, Policy
from crowdbench.envs.rules import segment_min_distance
from crowdbench.envs.world import World

PLANNED_SUCCESS, PLANNED_COLLISION, PLANNED_TIMEOUT = 1, 2, 3


class Oracle(Policy):
    """Privileged space-time beam-search planner (see the module docstring).

    Parameters: ``headings`` (16) directions, ``speeds`` ((1.0, 0.5) x v_max), ``beam`` (32)
    positions kept per episode and step, ``cell`` (0.1 m) de-duplication grid, ``danger_cost``
    (2.0 steps = 0.5 s per danger step; 1.0 leaves ~3x the danger steps on students003, 4.0 starts
    to trade success for timeouts), ``chunk`` (episodes planned together; memory bound).
    """

    name = "oracle"
    frame = "world"
    privileged = True

    def __init__(self, headings: int = OracleSettings.headings, speeds=ORACLE_SPEEDS, beam: int = OracleSettings.beam,
                 cell: float = OracleSettings.cell, danger_cost: float = OracleSettings.danger_cost,
                 chunk: int = OracleSettings.chunk):
        # the bounds of the oracle section (one line naming the key)
        OracleSettings(headings=headings, speeds=list(speeds), beam=beam, cell=cell, danger_cost=danger_cost, chunk=chunk)
        self.headings, self.speeds, self.beam = int(headings), tuple(float(s) for s in speeds), int(beam)
        self.cell, self.danger_cost, self.chunk = float(cell), float(danger_cost), int(chunk)
        self._plan: torch.Tensor | None = None
        self.planned_outcome: torch.Tensor | None = None
        self._k = 0

    # ------------------------------------------------------------------ Policy interface
    def plan(self, sim: World) -> None:
        """Privileged hook, called by :func:`crowdbench.protocols.replay.rollout` right after the reset:
        plan every episode of the batch from the simulator's scene, start indices, starts and goals."""
        plans, outcomes = [], []
        for lo in range(0, sim.B, self.chunk):
            sl = slice(lo, min(lo + self.chunk, sim.B))
            p, o = self._search(sim, sim.t[sl], sim.pos[sl, 0], sim.goal[sl, 0])
            plans.append(p)
            outcomes.append(o)
        self._plan = torch.cat(plans, 1)  # [T, B, 2] world velocities
        self.planned_outcome = torch.cat(outcomes)
        self._k = 0

    def reset(self, mask: torch.Tensor) -> None:
        self._k = 0

    def act(self, td: TensorDict) -> torch.Tensor:
        robot = td[OBS + ("robot",)]
        if self._plan is None or self._plan.shape[1] != robot.shape[0]:
            raise RuntimeError("the oracle is privileged: it acts only in rollouts that call plan(sim) "
                               "(crowdbench.protocols.replay.evaluate does)")
        k = self._k
        self._k += 1
        if k >= self._plan.shape[0]:
            return torch.zeros_like(robot[..., :2])
        return self._plan[k].unsqueeze(1).to(robot.dtype)

    # ------------------------------------------------------------------ search
    def _actions(self, to_goal: torch.Tensor, dist: torch.Tensor, v_max: float, dt: float) -> torch.Tensor:
        """Candidate world velocities ``[B, W, A, 2]`` for beams with goal offsets ``to_goal [B, W, 2]``."""
        gdir = to_goal / dist.clamp_min(1e-9).unsqueeze(-1)
        ang = torch.arange(self.headings, dtype=gdir.dtype) * (2 * math.pi / self.headings)
        c, s = torch.cos(ang), torch.sin(ang)  # [H]
        gx, gy = gdir[..., 0:1], gdir[..., 1:2]
        dirs = torch.stack((c * gx - s * gy, s * gx + c * gy), -1)  # [B, W, H, 2]
        sp = torch.tensor(self.speeds, dtype=gdir.dtype) * v_max
        moves = (dirs.unsqueeze(-2) * sp.view(-1, 1)).flatten(-3, -2)  # [B, W, H*S, 2]
        land = gdir * torch.minimum(dist / dt, torch.full_like(dist, v_max)).unsqueeze(-1)
        return torch.cat((moves, torch.zeros_like(land).unsqueeze(-2), land.unsqueeze(-2)), -2)

    @torch.no_grad()
    def _search(self, sim: World, t0: torch.Tensor, start: torch.Tensor, goal: torch.Tensor):
        cfg, scene = sim.cfg, sim.scene
        dt, v_max, T = cfg.dt, cfg.v_max, cfg.time_limit
        rs, r_goal, danger_dist = sim.radius_sum, cfg.robot_radius, cfg.danger_dist
        B, W, M = start.shape[0], self.beam, scene.max_humans
        dev = start.device
        ar_b = torch.arange(B, device=dev)
        pos = start.unsqueeze(1).expand(B, W, 2).clone()
        alive = torch.zeros(B, W, dtype=torch.bool)
        alive[:, 0] = True
        dangers = torch.zeros(B, W)
        best = torch.full((B,), math.inf)  # cost of the best finished plan
        best_k = torch.full((B,), -1, dtype=torch.long)  # its last step
        best_w = torch.zeros(B, dtype=torch.long)  # its beam at that step
        best_v = torch.zeros(B, 2)  # its last action
        fb_k = torch.zeros(B, dtype=torch.long)  # fallback: the best beam that survived longest
        fb_w = torch.zeros(B, dtype=torch.long)
        fb_f = torch.full((B,), math.inf)
        parents, vels = [], []
        inv_step = 1.0 / (v_max * dt)
        for k in range(T):
            if not alive.any():
                break
            t1 = t0 + k + 1
            h0, h1, hv = scene.prev[t1], scene.pos[t1], scene.valid[t1]  # [B, M, ...]
            # exact pruning: a human farther than reach from a beam cannot collide nor be in danger range
            gap = (h1.unsqueeze(1) - pos.unsqueeze(2)).norm(dim=-1) - rs  # [B, W, M]
            gap = gap.masked_fill(~hv.unsqueeze(1), math.inf)
            hstep = ((h1 - h0).norm(dim=-1) * hv).amax() if M else torch.tensor(0.0)
            reach = danger_dist + v_max * dt + float(hstep) + 1e-3
            need = int(((gap < reach) & alive.unsqueeze(-1)).sum(-1).amax()) if M else 0
            K = max(1, min(M, need))
            gk, idx = torch.topk(gap, K, dim=-1, largest=False)  # [B, W, K]
            idx2 = idx.flatten(1)
            g0 = torch.gather(h0, 1, idx2.unsqueeze(-1).expand(-1, -1, 2)).view(B, W, K, 2)
            g1 = torch.gather(h1, 1, idx2.unsqueeze(-1).expand(-1, -1, 2)).view(B, W, K, 2)
            gv = torch.isfinite(gk)
            # candidates: the simulator's own clipping and motion
            to_goal = goal.unsqueeze(1) - pos
            act = self._actions(to_goal, to_goal.norm(dim=-1), v_max, dt)  # [B, W, A, 2]
            A = act.shape[2]
            vel = sim.clip_action(act)
            new_pos = pos.unsqueeze(2) + vel * dt  # [B, W, A, 2]
            rel0 = (g0 - pos.unsqueeze(2)).unsqueeze(2)  # [B, W, 1, K, 2]
            rel1 = g1.unsqueeze(2) - new_pos.unsqueeze(3)  # [B, W, A, K, 2]
            swept = segment_min_distance(rel0.expand_as(rel1), rel1) - rs
            swept = swept.masked_fill(~gv.unsqueeze(2), math.inf).amin(-1)  # [B, W, A]
            end = ((g1.unsqueeze(2) - new_pos.unsqueeze(3)).norm(dim=-1) - rs)
            end = end.masked_fill(~gv.unsqueeze(2), math.inf).amin(-1)
            ok = alive.unsqueeze(-1) & (swept >= 0)
            dist1 = (goal.view(B, 1, 1, 2) - new_pos).norm(dim=-1)
            done = ok & (dist1 < r_goal)
            dcount = dangers.unsqueeze(-1) + ((end >= 0) & (end < danger_dist)).float()
            cost = (k + 1) + self.danger_cost * dcount  # [B, W, A]
            f = cost + (dist1 - r_goal).clamp_min(0) * inv_step
            # finished plans
            fin_cost = torch.where(done, cost, math.inf).flatten(1)
            c_min, c_arg = fin_cost.min(1)
            better = c_min < best
            best = torch.where(better, c_min, best)
            best_k = torch.where(better, k, best_k)
            best_w = torch.where(better, c_arg // A, best_w)
            best_v = torch.where(better.unsqueeze(-1), vel.flatten(1, 2)[ar_b, c_arg], best_v)
            # survivors: not finished, not collided, still able to beat the best finished plan
            keep = ok & ~done & (f < best.view(B, 1, 1))
            fk = torch.where(keep, f, math.inf).flatten(1)  # [B, W*A]
            # de-duplicate on the cell grid: cheapest candidate per cell (ties: lowest index)
            cellxy = torch.floor((new_pos - start.view(B, 1, 1, 2)) / self.cell).long() + 512
            cell = (cellxy[..., 0] * 1024 + cellxy[..., 1]).flatten(1)  # [B, W*A]
            order = torch.sort(fk, dim=1, stable=True).indices
            cell_sorted = torch.gather(cell, 1, order)
            key = ar_b.unsqueeze(1) * (1 << 21) + cell_sorted
            _, inv = torch.unique(key.flatten(), return_inverse=True)
            rank = torch.arange(key.numel(), device=dev)
            first = torch.full((int(inv.max()) + 1,), key.numel(), dtype=torch.long)
            first = first.scatter_reduce(0, inv, rank, "amin")
            is_first = (first[inv] == rank).view(B, -1)
            f_sorted = torch.gather(fk, 1, order)
            f_sorted = torch.where(is_first, f_sorted, math.inf)
            top_f, pick = torch.sort(f_sorted, dim=1, stable=True)
            top_f, pick = top_f[:, :W], pick[:, :W]
            if top_f.shape[1] < W:  # fewer candidates than the beam (A * W < W cannot happen; kept for safety)
                pad = W - top_f.shape[1]
                top_f = torch.cat((top_f, torch.full((B, pad), math.inf)), 1)
                pick = torch.cat((pick, torch.zeros(B, pad, dtype=torch.long)), 1)
            chosen = torch.gather(order, 1, pick)  # index into W*A
            alive = torch.isfinite(top_f)
            parent = chosen // A
            parents.append(parent)
            vels.append(torch.gather(vel.flatten(1, 2), 1, chosen.unsqueeze(-1).expand(-1, -1, 2)))
            pos = torch.gather(new_pos.flatten(1, 2), 1, chosen.unsqueeze(-1).expand(-1, -1, 2))
            dangers = torch.gather(dcount.flatten(1), 1, chosen)
            # fallback for episodes without a finished plan: the best beam of the deepest step
            has = alive.any(1)
            fb_k = torch.where(has, k + 1, fb_k)
            fb_w = torch.where(has, 0, fb_w)  # the beams are sorted: beam 0 is the cheapest
            fb_f = torch.where(has, top_f[:, 0], fb_f)
        # back-track: actions [T, B, 2]
        plan = torch.zeros(T, B, 2)
        success = best_k >= 0
        last = torch.where(success, best_k, fb_k - 1)  # last planned step index (-1: none)
        w = torch.where(success, best_w, fb_w)
        plan_steps = len(vels)
        for j in range(plan_steps - 1, -1, -1):
            # success plans: step best_k uses best_v, earlier steps come from the beam history
            at_end = success & (j == best_k)
            inside = j < last
            on_fb = ~success & (j == last)
            v_hist = vels[j][ar_b, w]
            plan[j] = torch.where(at_end.unsqueeze(-1), best_v, torch.where((inside | on_fb).unsqueeze(-1), v_hist,
                                                                           plan[j]))
            w = torch.where(inside | on_fb, parents[j][ar_b, w], w)
        outcome = torch.where(success, PLANNED_SUCCESS,
                              torch.where(fb_k >= T, PLANNED_TIMEOUT, PLANNED_COLLISION))
        return plan, outcome
