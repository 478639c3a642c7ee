"""ORCA (RVO2, via the ``pyrvo`` wheel) for the robot among replayed, non-reacting humans.

This is the classical baseline of the paper (and of CrowdNav): at every step one RVO2
simulator is built per environment with the robot and the humans it observes, one RVO2
step is solved, and only the robot's new velocity is read back.

pyrvo API facts this module relies on (pyrvo 0.4.3, RVO2 2.0 sources vendored in the wheel):

- ``RVOSimulator(timeStep, neighborDist, maxNeighbors, timeHorizon, timeHorizonObst,
  radius, maxSpeed[, velocity])`` sets the agent defaults; ``add_agent(position,
  neighborDist, maxNeighbors, timeHorizon, timeHorizonObst, radius, maxSpeed, velocity)``
  returns the agent index. Positions and velocities accept any length-2 sequence (a
  tuple of Python floats is the cheapest); getters return ``pyrvo.Vector2`` (``.x``,
  ``.y``, ``.to_tuple()``). Everything is single precision inside.
- ``do_step`` computes every agent's new velocity from the *current* velocities, then
  moves all agents; the robot's ORCA lines use the humans' ``velocity``, never their
  preferred velocity.
- ``clear_agents`` must not be used to recycle a simulator: the k-d tree caches agent
  pointers and only refreshes them when the agent count grows, so re-adding as many or
  fewer agents leaves dangling pointers. A fresh simulator is cheap (~1 us), so one is
  built per environment and step.
"""

from __future__ import annotations

import math

import numpy as np
import pyrvo
import torch
from tensordict import TensorDict

from crowdbench.baselines.params import OrcaSettings
from crowdbench.envs.observation import OBS, Policy

_TWO_PI = 2.0 * math.pi


def _mix32(h: np.ndarray) -> np.ndarray:
    """A 32-bit integer finaliser (murmur3 ``fmix32``) applied elementwise."""
    h = h ^ (h >> np.uint32(16))
    h = h * np.uint32(0x85EBCA6B)
    h = h ^ (h >> np.uint32(13))
    h = h * np.uint32(0xC2B2AE35)
    return h ^ (h >> np.uint32(16))


def perturbation_angle(robot: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random angle in ``[0, 2*pi)`` per row of ``robot`` (``[N, 6]`` float32).

    The hash is computed from the exact bit patterns of each row, column by column, so it
    depends only on that environment's inputs and the seed: the same observation always
    gets the same perturbation, whatever the batch it is in.
    """
    bits = np.ascontiguousarray(robot, dtype=np.float32).view(np.uint32)
    with np.errstate(over="ignore"):
        h = np.full(bits.shape[0], np.uint32(seed & 0xFFFFFFFF) ^ np.uint32(0x9E3779B9), dtype=np.uint32)
        for j in range(bits.shape[1]):
            h = _mix32(h ^ (bits[:, j] + np.uint32(0x9E3779B9 * (j + 1) & 0xFFFFFFFF)))
    return h.astype(np.float64) * (_TWO_PI / 2.0**32)


class ORCA(Policy):
    """ORCA for the robot; humans are ORCA agents that follow their replayed velocities.

    Parameters (defaults in parentheses; why each is chosen):

    - ``v_max`` (1.0), ``dt`` (0.25), ``robot_radius`` (0.2), ``human_radius`` (0.1): the
      protocol's values (SPEC section 3), so ORCA avoids exactly the bodies the simulator
      tests collisions against.
    - ``safety_margin`` (0.2 m, added to every human's radius): ORCA assumes reciprocity and
      takes only half of each avoidance manoeuvre, but the replayed humans never react to
      the invisible robot, so with the bare radii the robot plans to graze every human it
      avoids and collides with many of them (students001, margin 0: ~70 % of episodes
      end in collision, straight-to-goal ~80 %). An inflated radius buys back the missing
      half; CrowdNav's own comment on its invisible-robot setting suggests the same remedy. The
      value was tuned with ``time_horizon`` on the training scene only (students001, 5 x 250
      episodes): 0.05-0.15 m still collide noticeably, 0.25-0.3 m start to refuse gaps and
      time out. ORCA then keeps centres >= 0.5 m apart whenever its plan holds.
    - ``time_horizon`` (2.0 s): how far ahead collisions are avoided. With non-reacting
      humans, long horizons (CrowdNav's 5 s) make the crowd's velocity obstacles overlap
      so that the robot hesitates; on students001 5 s had both more timeouts and more
      collisions, 2-3 s were best, and 2 s had about half the collisions of 3 s at equal
      success.
    - ``neighbor_dist`` (5.0 m): the sensing range; every observed human is a candidate
      neighbour and nobody the robot cannot see is ever used.
    - ``max_neighbors`` (10): RVO2 keeps the nearest ones. With a 2 s horizon the eleventh
      nearest human in a 5 m disc rarely constrains the answer: on students001, using all
      observed humans (up to ~50) changed success and collisions only within noise
      (2 x 250 episodes) and costs more. CrowdNav's default as well.
    - ``time_horizon_obst`` (5.0 s): no static obstacles are used; kept for completeness.
    - ``perturb`` (1e-3 m/s): exact symmetries make ORCA's linear program answer with a pure
      slow-down and no lateral component. Measured: a robot heading straight at a standing
      human stops in front of it and never passes unless the preferred velocity is
      perturbed, while 1e-4 .. 1e-2 all resolve it. The perturbation is added at an angle
      hashed from the exact bits of the robot's observation row and ``seed``, so it is
      deterministic (same inputs give the same outputs, whatever the batch), unlike RVO2's
      examples, which draw it from ``rand()``.
    - ``frame`` ("rotate"): any observation frame works (ORCA is invariant to rotations and
      translations); actions are returned in the frame of the observation.

    The preferred velocity points at the goal at ``v_max``, slowed to ``dist / dt`` near
    the goal so the robot does not overshoot it (``pref_rule="reach"``); ``pref_rule="crowdnav"``
    slows to ``dist`` m/s within ``v_max`` metres instead, as CrowdNav's ORCA (env=crowdnav uses it: it
    arrives ~0.3 s later on average, CrowdNav's published times). Humans get their replayed velocity as both
    velocity and preferred velocity and ``maxNeighbors = 0``: their own new velocities are
    never read, so they need no neighbour search (this keeps ``do_step`` at about one
    k-d tree build plus the robot's linear program). Only humans flagged in ``humans_mask``
    are added. Each robot of a multi-robot batch is solved on its own.
    """

    name = "orca"

    def __init__(
        self,
        v_max: float = 1.0,
        dt: float = 0.25,
        robot_radius: float = 0.2,
        human_radius: float = 0.1,
        safety_margin: float = OrcaSettings.safety_margin,
        neighbor_dist: float = OrcaSettings.neighbor_dist,
        max_neighbors: int = OrcaSettings.max_neighbors,
        time_horizon: float = OrcaSettings.time_horizon,
        time_horizon_obst: float = 5.0,
        perturb: float = OrcaSettings.perturb,
        pref_rule: str = OrcaSettings.pref_rule,
        seed: int = 0,
        frame: str = "rotate",
    ):
        if frame not in ("rotate", "translate", "world"):
            raise ValueError(f"unknown frame {frame!r}; valid: rotate, translate, world")
        # the bounds of the orca section (one line naming the key)
        OrcaSettings(safety_margin=safety_margin, time_horizon=time_horizon, max_neighbors=max_neighbors,
                     neighbor_dist=neighbor_dist, perturb=perturb, pref_rule=pref_rule)
        if not time_horizon_obst > 0:
            raise ValueError(f"orca.time_horizon_obst: must be > 0 (got {time_horizon_obst!r})")
        self.v_max, self.dt = float(v_max), float(dt)
        self.robot_radius, self.human_radius = float(robot_radius), float(human_radius)
        self.safety_margin = float(safety_margin)
        self.neighbor_dist, self.max_neighbors = float(neighbor_dist), int(max_neighbors)
        self.time_horizon, self.time_horizon_obst = float(time_horizon), float(time_horizon_obst)
        self.perturb, self.seed = float(perturb), int(seed)
        self.pref_rule = pref_rule
        self.frame = frame

    @classmethod
    def from_config(cls, cfg) -> ORCA:
        """ORCA as ``policy=orca`` builds it from a composed config (dict or DictConfig): the ``orca`` section,
        the env's dynamics, the seed, in the env's observation frame (the warm start's expert, a residual's base)."""
        from crowdbench.baselines.params import params

        return cls(**params("orca", cfg), frame=cfg["env"]["frame"])

    def preferred_velocity(self, robot: np.ndarray) -> np.ndarray:
        """``[N, 2]`` preferred velocities (float64) for ``[N, 6]`` robot rows, perturbed."""
        r = robot.astype(np.float64)
        to_goal = r[:, 4:6] - r[:, 0:2] if self.frame == "world" else r[:, 4:6]
        dist = np.linalg.norm(to_goal, axis=1, keepdims=True)
        # reach: land on the goal in one step; crowdnav: min(dist, 1) m/s as CrowdNav's orca.py l.113-115
        speed = np.minimum(dist / self.dt if self.pref_rule == "reach" else dist, self.v_max)
        pref = to_goal / np.maximum(dist, 1e-9) * speed
        if self.perturb > 0.0:
            ang = perturbation_angle(robot, self.seed)
            pref = pref + self.perturb * np.stack((np.cos(ang), np.sin(ang)), 1)
        return pref

    def act(self, td: TensorDict) -> torch.Tensor:
        return self.velocities(td[OBS + ("robot",)], td[OBS + ("humans",)], td[OBS + ("humans_mask",)])

    @torch.no_grad()
    def velocities(self, robot_t: torch.Tensor, humans_t: torch.Tensor, mask_t: torch.Tensor) -> torch.Tensor:
        """ORCA's new velocity ``[*, 2]`` for observations ``[*, 6], [*, M, 4], [*, M]``."""
        lead = robot_t.shape[:-1]  # [B, A]
        robot = robot_t.detach().reshape(-1, 6).to(torch.float32).cpu().numpy()
        n = robot.shape[0]
        mask = mask_t.detach().reshape(n, -1).cpu().numpy().astype(bool)
        humans = humans_t.detach().reshape(n, mask.shape[1], 4).cpu().numpy()

        pref = self.preferred_velocity(robot).tolist()
        rpos = robot[:, 0:2].tolist()
        rvel = robot[:, 2:4].tolist()
        seen = humans[mask].tolist()  # [K, 4] observed humans, env-major
        ends = np.cumsum(mask.sum(1)).tolist()

        dt, nd, mn = self.dt, self.neighbor_dist, self.max_neighbors
        th, tho = self.time_horizon, self.time_horizon_obst
        rr, vm = self.robot_radius, self.v_max
        hr = self.human_radius + self.safety_margin
        sim_cls = pyrvo.RVOSimulator
        out = np.empty((n, 2), dtype=np.float32)
        start = 0
        for i in range(n):
            sim = sim_cls(dt, nd, mn, th, tho, rr, vm)
            add, set_pref = sim.add_agent, sim.set_agent_pref_velocity
            add(tuple(rpos[i]), nd, mn, th, tho, rr, vm, tuple(rvel[i]))
            set_pref(0, tuple(pref[i]))
            end = ends[i]
            for k in range(start, end):
                px, py, vx, vy = seen[k]
                v = (vx, vy)
                # max speed irrelevant (their new velocity is never read); keep theirs feasible
                set_pref(add((px, py), nd, 0, th, tho, hr, vm + abs(vx) + abs(vy), v), v)
            start = end
            sim.do_step()
            out[i] = sim.get_agent_velocity(0).to_tuple()
        return torch.from_numpy(out).reshape(*lead, 2).to(robot_t.device)
