"""The batched world: ``B`` environments of ``A`` learning agents (robots) and ``M`` humans.

One world serves every protocol (the VMAS idea): a **crowd model** (:mod:`crowdbench.envs.humans`)
moves the humans (replayed ETH/UCY tracks, ORCA, social force, or none) and a **scenario**
(:mod:`crowdbench.envs.scenarios`) places agents, humans and goals. Every tensor is batch-first;
one :meth:`World.step` advances all environments with tensor ops; resets take a boolean mask.

Geometry (SPEC section 3), the same for every crowd model:

- clearance ``d`` = centre distance - sum of the two radii;
- collision: ``d < 0`` at any moment of the step, tested on the linear motion of both bodies over
  the step (closest approach of the relative segment, :func:`segment_min_distance`);
- danger: ``0 <= d < danger_dist`` at the end of a step; success: distance to goal < robot radius.

The humans' motion over a step is decided from the state at its start (a reactive crowd model
sees the agents where they are, with the velocity they had), then all bodies move together.

With ``interact=True`` (self-play) agents are bodies for each other too:

- agent-agent clearance ``d = |p_i - p_j| - 2 robot_radius``; a swept ``d < 0`` is a collision of
  *both* agents (``StepInfo.extra["pair_collision"]`` ``[B, A, A]``); the danger penalty uses the
  nearest body, agent or human;
- a done agent no longer moves and gets zero reward while the others go on; ``done_agents="vanish"``:
  it leaves the scene (others neither sense nor hit it); ``"obstacle"``: it stays as a static body;
- agent ``i`` observes ``A + M`` slots, the ``A`` agents first (its own slot masked), then the humans,
  so a shared-weight graph policy sees every other agent as a neighbour node.

Without it (the robot protocols) each robot observes the ``M`` humans only.

Memory: the all-pairs tests (agent-agent and agent-human clearances, each agent's view before its
``obs_slots`` nearest are kept) run over blocks of agent rows, at most ``PAIRS`` pairs a block
(:meth:`World._blocks`), so their intermediates do not grow with ``A`` or ``B``: with ``obs_slots`` a step
holds ``O(B A)`` tensors, plus the ``[B, A, A]`` booleans of ``pair_collision`` (without it the view itself is
``[B, A, A + M, 4]``). A block's values are the same bits as the same rows of the all-pairs tensors (the same
elementwise operations, the same reductions and nearest-slot selection over each row).
"""

from __future__ import annotations

import torch

from crowdbench.envs.humans import Agents
from crowdbench.envs.rules import (
    _FAR,
    RUNNING,
    TIMEOUT,
    SimConfig,
    StepInfo,
    outcome_of,
    segment_min_distance,
    step_reward,
)
from crowdbench.kinematics import advance, clip_speed, heading_to, to_local, to_world

DONE_AGENTS = ("vanish", "obstacle")
# pairs (over the whole batch) in one block of the all-pairs tests: a block's float tensors are 256 kB, as
# fast as or faster than larger blocks on CPU (B = 64: 1024 pairs per environment, 32 agents in one block)
PAIRS = 65536


class World:
    """``B`` environments, ``A`` agents each, humans moved by ``crowd`` (a :class:`~crowdbench.envs.humans.Crowd`)."""

    def __init__(self, batch: int, cfg: SimConfig, crowd, n_agents: int = 1, interact: bool = False,
                 done_agents: str = "vanish"):
        if done_agents not in DONE_AGENTS:
            raise ValueError(f"unknown done_agents {done_agents!r}; valid: {', '.join(DONE_AGENTS)}")
        if n_agents < 1:
            raise ValueError(f"n_agents must be >= 1, got {n_agents}")
        if not isinstance(batch, int) or batch < 1:
            raise ValueError(f"batch (env.batch) must be a positive integer, got {batch!r}")
        self.cfg, self.crowd = cfg, crowd
        self.B, self.A, self.Mh = batch, n_agents, crowd.M
        self.interact, self.done_agents = interact, done_agents
        self.M = (n_agents if interact else 0) + crowd.M  # observed slots per agent
        # the nearest obs_slots bodies only (self-play's env.obs_slots; 0: every slot)
        self.slots = min(int(getattr(cfg, "obs_slots", 0) or self.M), self.M)
        self.M_all, self.M = self.M, self.slots
        B, A = batch, n_agents
        self.steps = torch.zeros(B, dtype=torch.long)
        self.pos = torch.zeros(B, A, 2)
        self.vel = torch.zeros(B, A, 2)
        self.goal = torch.zeros(B, A, 2)
        self.start = torch.zeros(B, A, 2)
        self.heading = torch.zeros(B, A, 2)
        self.heading[..., 0] = 1.0
        self.outcome = torch.full((B, A), TIMEOUT, dtype=torch.long)  # not started = finished
        self.eye = torch.eye(A, dtype=torch.bool)
        self.r_aa = 2 * cfg.robot_radius
        self.radius_sum = cfg.robot_radius + cfg.human_radius

    # the replay crowd's scene and time index (the oracle and the recorder read them)
    @property
    def scene(self):
        return getattr(self.crowd, "scene", None)

    @property
    def t(self) -> torch.Tensor:
        return self.crowd.t

    # ------------------------------------------------------------------ episodes
    def reset(self, mask: torch.Tensor, episode: dict[str, torch.Tensor]) -> None:
        """Start new episodes where ``mask`` ([B] bool) is set; ``episode`` holds ``[n, ...]`` tensors
        for the ``n`` masked environments in order: ``start``, ``goal`` ``[n, A, 2]`` (world frame)
        and what the crowd model needs (e.g. ``t0`` for replay, ``human_start``/``human_goal``)."""
        idx = mask.nonzero().squeeze(-1)
        if len(idx) != len(episode["start"]):
            raise ValueError(f"{len(episode['start'])} episodes for {len(idx)} environments")
        self.crowd.reset(mask, idx, episode)
        start, goal = episode["start"].to(self.pos.dtype), episode["goal"].to(self.pos.dtype)
        self.steps[idx] = 0
        self.start[idx] = start
        self.pos[idx] = start
        self.goal[idx] = goal
        self.vel[idx] = 0.0
        self.outcome[idx] = RUNNING
        self._update_heading()

    def _update_heading(self) -> None:
        self.heading = heading_to(self.goal, self.pos, self.heading)

    # ------------------------------------------------------------------ bodies
    def present(self) -> torch.Tensor:
        """``[B, A]``: agents that are bodies in the scene (running, or done and kept as obstacles)."""
        if self.done_agents == "obstacle":
            return torch.ones_like(self.outcome, dtype=torch.bool)
        return self.outcome == RUNNING

    def agents(self) -> Agents:
        """The agents as the crowd model sees them (its whole view of the world, crowdbench/envs/humans)."""
        return Agents(self.pos, self.vel, self.present())

    def _pair_mask(self, present: torch.Tensor, rows: slice = slice(None)) -> torch.Tensor:
        """``[B, R, A]``: agent ``j`` is a body agent ``i`` (of ``rows``) can meet (not itself)."""
        return present.unsqueeze(1) & ~self.eye[rows]

    def humans(self):
        """Humans now: position, velocity ``[B, M, 2]``, present ``[B, M]``."""
        return self.crowd.observe()

    def human_clearance(self, pos: torch.Tensor | None = None, rows: slice = slice(None)) -> torch.Tensor:
        """Per-human clearance ``[B, A, M]`` of agents at ``pos`` (default: now); ``_FAR`` on padding;
        ``rows``: those agents only."""
        pos = (self.pos if pos is None else pos)[:, rows]
        hpos, _, hvalid = self.humans()
        gap = (hpos.unsqueeze(1) - pos.unsqueeze(2)).norm(dim=-1) - self.radius_sum
        return gap.masked_fill(~hvalid.unsqueeze(1), _FAR)

    def agent_clearance(self, rows: slice = slice(None)) -> torch.Tensor:
        """``[B, A, A]`` surface gaps between agents (``_FAR`` for itself and absent agents); ``rows``: the
        gaps of those agents only, ``[B, R, A]``."""
        gap = (self.pos.unsqueeze(1) - self.pos[:, rows].unsqueeze(2)).norm(dim=-1) - self.r_aa
        return gap.masked_fill(~self._pair_mask(self.present(), rows), _FAR)

    def nearest_agent(self) -> torch.Tensor:
        """``[B, A]``: ``agent_clearance().amin(-1)``, one block of rows at a time."""
        return self._blocks(self.A, lambda r: (self.agent_clearance(r).amin(-1),))[0]

    def min_clearance(self) -> torch.Tensor:
        """Current clearance to the nearest body (human, or agent when agents interact), ``[B, A]``."""
        if not self.M_all:
            return torch.full((self.B, self.A), _FAR)

        def rows(r: slice):
            gap = self.human_clearance(rows=r)
            if self.interact:
                gap = torch.cat((self.agent_clearance(r), gap), -1)
            return (gap.amin(-1),)

        return self._blocks(self.M_all, rows)[0]

    def _blocks(self, width: int, fn, batch: int | None = None) -> tuple[torch.Tensor, ...]:
        """``fn(rows)`` for blocks of agent rows of at most ``PAIRS`` pairs of ``width`` columns over
        ``batch`` environments (default ``B``), its tensors (agents on dim 1) stitched together: only one
        block's pair tensors are alive at a time."""
        size = max(1, PAIRS // max((batch or self.B) * width, 1))
        if size >= self.A:  # one block: fn's own tensors
            return fn(slice(None))
        out = None
        for i in range(0, self.A, size):
            r = slice(i, i + size)
            part = fn(r)
            if out is None:
                out = tuple(p.new_empty(p.shape[0], self.A, *p.shape[2:]) for p in part)
            for o, p in zip(out, part):
                o[:, r] = p
        return out

    def clip_action(self, action: torch.Tensor) -> torch.Tensor:
        return clip_speed(action, self.cfg.v_max)

    # ------------------------------------------------------------------ step
    def step(self, action: torch.Tensor, frame: str | None = None) -> StepInfo:
        """Advance every running agent and the crowd by one step.

        ``action`` is ``[B, A, 2]`` velocity in the observation frame (``frame``, default the
        config's). Finished agents stay frozen (zero reward) until their environment resets.
        ``extra``: ``human_clearance`` ``[B, A]``; with ``interact``, also ``pair_collision``
        ``[B, A, A]`` and ``agent_clearance`` ``[B, A]`` (end-of-step gap to the nearest agent).
        """
        if not torch.isfinite(action).all():  # inf would become NaN in the frame rotation
            raise ValueError("action contains NaN or inf")
        cfg = self.cfg
        frame = frame or cfg.frame
        act = to_world(action.unsqueeze(-2), self.heading).squeeze(-2) if frame == "rotate" else action
        active = self.outcome == RUNNING  # [B, A]
        vel = self.clip_action(act) * active.unsqueeze(-1)
        new_pos = advance(self.pos, vel, cfg.dt)
        env_active = active.any(-1)

        # humans move from h0 to h1 over the step (decided from the state at its start)
        h0, h1, hv1 = self.crowd.advance(env_active, self.agents())
        swept_h, end_h = self._human_gaps(h0, h1, hv1, new_pos)
        extra = {"human_clearance": end_h}
        hit = swept_h < 0
        end, swept = end_h, swept_h
        if self.interact:  # agents: both bodies move linearly (a done obstacle does not move)
            hit_aa, agent_end, swept_a = self._agent_gaps(new_pos, active)
            pair_hit = hit_aa.transpose(1, 2) & active.unsqueeze(-1)  # both agents of a running pair
            pair_hit |= hit_aa
            end, swept = torch.minimum(agent_end, end_h), torch.minimum(swept_a, swept_h)
            hit = pair_hit.any(-1) | hit
            extra.update(pair_collision=pair_hit, agent_clearance=agent_end)

        steps = self.steps + env_active.long()
        collision = active & hit
        success = active & ~collision & ((self.goal - new_pos).norm(dim=-1) < cfg.robot_radius)
        timeout = active & ~collision & ~success & (steps >= cfg.time_limit).unsqueeze(-1)

        reward = step_reward(cfg, end, swept, success, collision, timeout, active)
        outcome = outcome_of(success, collision, timeout)
        self.outcome = torch.where(active, outcome, self.outcome)
        self.pos, self.vel, self.steps = new_pos, vel, steps
        self._update_heading()
        return StepInfo(reward=reward, terminated=success | collision, truncated=timeout, outcome=outcome,
                        clearance=end, swept_clearance=swept, active=active, extra=extra)

    def _human_gaps(self, h0, h1, hv1, new_pos) -> tuple[torch.Tensor, torch.Tensor]:
        """Swept and end-of-step clearance ``[B, A]`` of every agent to its nearest human (``_FAR``: none)."""
        if not self.Mh:
            far = torch.full((self.B, self.A), _FAR)
            return far, far
        gone = ~hv1.unsqueeze(1)

        def rows(r: slice):
            p0, p1 = self.pos[:, r].unsqueeze(2), new_pos[:, r].unsqueeze(2)
            swept = segment_min_distance(h0.unsqueeze(1) - p0, h1.unsqueeze(1) - p1) - self.radius_sum
            swept = swept.masked_fill(gone, _FAR)
            end = ((h1.unsqueeze(1) - p1).norm(dim=-1) - self.radius_sum).masked_fill(gone, _FAR)
            return swept.amin(-1), end.amin(-1)

        return self._blocks(self.Mh, rows)

    def _agent_gaps(self, new_pos, active) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Agent-agent tests of a step: ``hit`` ``[B, i, j]`` (running ``i`` sweeps into present ``j``), and
        each agent's end-of-step and swept clearance ``[B, A]`` to its nearest agent (``_FAR``: none)."""
        present = self.present()

        def rows(r: slice):
            pair = self._pair_mask(present, r) & active[:, r].unsqueeze(-1)  # [B, i, j]: i can hit j
            rel0 = self.pos.unsqueeze(1) - self.pos[:, r].unsqueeze(2)  # [B, i, j, 2] = p_j - p_i
            rel1 = new_pos.unsqueeze(1) - new_pos[:, r].unsqueeze(2)
            swept = (segment_min_distance(rel0, rel1) - self.r_aa).masked_fill(~pair, _FAR)
            end = (rel1.norm(dim=-1) - self.r_aa).masked_fill(~pair, _FAR)
            return swept < 0, end.amin(-1), swept.amin(-1)

        return self._blocks(self.A, rows)

    # ------------------------------------------------------------------ observation
    def observe(self, frame: str | None = None, rows: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Each agent's view in its own frame (SPEC section 3; layout in :mod:`crowdbench.envs.observation`).

        - ``robot`` ``[B, A, 6]``: ``[px, py, vx, vy, gx, gy]`` (position 0 in relative frames);
        - ``humans`` ``[B, A, S, 4]``: ``[px, py, vx, vy]`` of every slot, zero where unobserved;
        - ``humans_mask`` ``[B, A, S]``: present and within the sensing range (centre distance).

        ``rows`` (environment indices): the views of those environments only, ``[len(rows), ...]``; every
        value is computed per environment, so they are the same bits as the full batch's rows.
        """
        frame = frame or self.cfg.frame
        pick = (lambda x: x) if rows is None else (lambda x: x[rows])
        opos, ovel, ovalid = (pick(x) for x in self.humans())
        pos, vel, goal, heading = pick(self.pos), pick(self.vel), pick(self.goal), pick(self.heading)
        if self.interact:
            opos, ovel = torch.cat((pos, opos), 1), torch.cat((vel, ovel), 1)
            ovalid = torch.cat((pick(self.present()), ovalid), 1)
        own = torch.stack((vel, goal - pos if frame != "world" else goal), -2)  # [B, A, 2, 2]
        if frame == "rotate":
            own = to_local(own, heading)
        origin = pos if frame == "world" else torch.zeros_like(pos)
        robot = torch.cat((origin, own.flatten(-2)), -1)
        view = lambda r: self._view(frame, (opos, ovel, ovalid), pos[:, r], heading[:, r], r)
        humans, seen = self._blocks(self.M_all, view, len(pos))
        return {"robot": robot, "humans": humans, "humans_mask": seen}

    def _view(self, frame: str, others, pos, heading, r: slice) -> tuple[torch.Tensor, torch.Tensor]:
        """The slots ``[B, R, M, 4]`` and mask ``[B, R, M]`` of the agents of rows ``r`` (at ``pos``, facing
        ``heading``, ``[B, R, 2]``) on the ``S`` bodies ``others`` (position, velocity, present)."""
        opos, ovel, ovalid = others
        rel = opos.unsqueeze(1) - pos.unsqueeze(2)  # [B, R, S, 2]
        seen = ovalid.unsqueeze(1) & ((rel * rel).sum(-1) <= self.cfg.sensing_range**2)
        if self.interact:
            seen[:, :, : self.A] &= ~self.eye[r]
        if frame == "rotate":  # elementwise: the same bits whatever the tensor it is applied to
            rel = to_local(rel, heading)
        near = rel  # slots are ranked by the relative position in the view's axes (rotated or not)
        if frame == "world":
            rel = opos.unsqueeze(1).expand_as(near)
        vel = ovel.unsqueeze(1).expand_as(near)
        if self.M < self.M_all:  # only the kept slots' features are built
            idx, seen = self._nearest(near, seen)
            idx = idx.unsqueeze(-1).expand(*idx.shape, 2)
            rel, vel = rel.gather(-2, idx), vel.gather(-2, idx)
        if frame == "rotate":
            vel = to_local(vel, heading)
        return torch.cat((rel, vel), -1) * seen.unsqueeze(-1), seen

    def _nearest(self, rel, seen) -> tuple[torch.Tensor, torch.Tensor]:
        """Indices ``[B, R, M]`` of the ``M`` nearest seen slots (``rel`` ``[B, R, S, 2]``), nearest first
        (unseen ones last), and whether each is seen."""
        d2 = (rel * rel).sum(-1).masked_fill(~seen, float("inf"))
        idx = d2.topk(self.M, dim=-1, largest=False, sorted=True).indices
        return idx, seen.gather(-1, idx)

    def scene_view(self) -> dict[str, torch.Tensor]:
        """Each agent's view of the whole scene, for a centralised critic (``algo=mappo``): every body,
        with no sensing range, and the other agents' goals, which no agent observes.

        - ``scene`` ``[B, A, N, 7]``: ``[px, py, vx, vy, gx, gy, is_agent]`` of every slot in the agent's
          frame (``env.frame``), position and goal relative to the agent; ``N`` = the observation's slots
          (the ``A`` agents first in self-play, then the humans); a human's goal is zero (unknown);
        - ``scene_mask`` ``[B, A, N]``: the slot is a body in the scene (not the agent itself).
        """
        frame = self.cfg.frame
        A = self.A
        opos, ovel, ovalid = self.humans()
        ogoal, kind = torch.zeros_like(opos), torch.zeros_like(opos[..., 0])
        if self.interact:
            opos, ovel = torch.cat((self.pos, opos), 1), torch.cat((self.vel, ovel), 1)
            ogoal, kind = torch.cat((self.goal, ogoal), 1), torch.cat((torch.ones_like(self.pos[..., 0]), kind), 1)
            ovalid = torch.cat((self.present(), ovalid), 1)
        mask = ovalid.unsqueeze(1).expand(-1, A, -1).clone()
        if self.interact:
            mask[:, :, :A] &= ~self.eye
        origin = self.pos.unsqueeze(2) if frame != "world" else torch.zeros_like(self.pos).unsqueeze(2)
        rel = opos.unsqueeze(1) - origin
        goal = (ogoal.unsqueeze(1) - origin) * kind[:, None, :, None]
        vel = ovel.unsqueeze(1).expand_as(rel)
        if frame == "rotate":
            rel, vel, goal = (to_local(x, self.heading) for x in (rel, vel, goal))
        feats = torch.cat((rel, vel, goal, kind[:, None, :, None].expand(*rel.shape[:-1], 1)), -1)
        return {"scene": feats * mask.unsqueeze(-1), "scene_mask": mask}
