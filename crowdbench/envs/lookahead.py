"""One-step lookahead candidates: for every environment and every action of a discrete set, where the
robot would be after one step, where the humans would be, and the reward the world would pay.

CrowdNav's value-based policies (CADRL, LSTM-RL, SARL; Chen et al. 2019) act by
``argmax_a r(s, a) + gamma^(dt v_pref) V(s'_a)``. The candidates are computed here, on the harness side
of the worker boundary, from the world itself, and handed to the policy with its observation
(:func:`lookahead_observation`), so a submission never touches the simulator. Two models of the humans'
next state:

- ``query`` (**privileged**, CrowdNav's ``query_env = true``): the world's actual next human states. With
  an invisible robot the humans' motion does not depend on the robot's action, so one advance of a copy
  of the crowd gives them for all actions, bit for bit what the next :meth:`World.step` will do;
- ``cv`` (not privileged): every human keeps its current velocity for one step.

The robot's candidate motion and its reward use the world's own operations in the world's order
(frame rotation, speed clip, swept collision test, :func:`~crowdbench.envs.rules.step_reward`), so with
``query`` the candidate of the action taken is the step that follows.
"""

from __future__ import annotations

import copy
import math

import torch

from crowdbench.envs.rules import _FAR, RUNNING, segment_min_distance, step_reward
from crowdbench.kinematics import advance, to_local, to_world

MODELS = ("query", "cv")
PRIVILEGED_MODELS = ("query",)
KINEMATICS = ("holonomic", "unicycle")
KEYS = ("cand_robot", "cand_reward", "cand_done", "cand_humans", "cand_humans_mask", "cand_running")


def action_set(v_pref: float, speeds: int = 5, headings: int = 16, kinematics: str = "holonomic") -> torch.Tensor:
    """``[1 + speeds * headings, 2]`` velocities in the robot frame (x towards the goal): stop, then every
    heading x speed, speeds spaced exponentially up to ``v_pref`` as CrowdNav's ``build_action_space``
    (``(e^(i/n) - 1) / (e - 1) v_pref``). Holonomic: headings evenly spaced over the full circle starting
    at the goal direction (CrowdNav spaces them from the world's x axis; its robot goes straight up, so
    the goal direction is in its set at the start too). Unicycle: headings in [-pi/4, pi/4] around the
    goal direction (CrowdNav's rotations, here relative to the goal instead of the robot's heading)."""
    if kinematics not in KINEMATICS:
        raise ValueError(f"unknown kinematics {kinematics!r}; valid: {', '.join(KINEMATICS)}")
    if speeds < 1 or headings < 1:
        raise ValueError(f"need speeds >= 1 and headings >= 1, got {speeds}, {headings}")
    v = torch.tensor([(math.exp((i + 1) / speeds) - 1) / (math.e - 1) * v_pref for i in range(speeds)],
                     dtype=torch.float64)
    if kinematics == "holonomic":
        rot = torch.arange(headings, dtype=torch.float64) * (2 * math.pi / headings)
    else:
        rot = torch.linspace(-math.pi / 4, math.pi / 4, headings, dtype=torch.float64)
    r, s = torch.meshgrid(rot, v, indexing="ij")  # heading-major, as CrowdNav's itertools.product
    moves = torch.stack((s * torch.cos(r), s * torch.sin(r)), -1).reshape(-1, 2)
    return torch.cat((torch.zeros(1, 2, dtype=torch.float64), moves)).to(torch.float32)


def next_humans(world, model: str):
    """The humans' next ``(pos, vel, valid)`` ``[B, M, 2]`` under lookahead ``model``; the world is unchanged."""
    if model not in MODELS:
        raise ValueError(f"unknown lookahead model {model!r}; valid: {', '.join(MODELS)}")
    pos, vel, valid = world.humans()
    if model == "cv":
        return advance(pos, vel, world.cfg.dt), vel, valid
    if getattr(world.crowd, "robot_visible", False) or world.interact:
        raise ValueError("lookahead=query needs an invisible robot: the humans' next state would depend on the action")
    # the crowd's advance replaces its tensors (never writes into them): a shallow copy leaves the world's intact;
    # the same batch and active mask as World.step, so the same arithmetic and the same bits
    crowd = copy.copy(world.crowd)
    crowd.advance((world.outcome == RUNNING).any(-1), world.agents())
    # what the crowd reports after the step (replay: the recorded velocity at t+1; reactive: its new velocity)
    return crowd.observe()


def candidates(world, actions: torch.Tensor, model: str) -> dict[str, torch.Tensor]:
    """Every action of ``actions`` ``[K, 2]`` (robot frame) for robot 0 of every environment, world frame:
    ``robot_pos``/``robot_vel`` ``[B, K, 2]``, ``humans_pos``/``humans_vel`` ``[B, M, 2]``, ``humans_valid``
    ``[B, M]`` (present and within the sensing range now: what the robot observes), ``reward`` ``[B, K]`` (the world's reward of that step), ``done`` ``[B, K]`` (success or collision)."""
    cfg = world.cfg
    B, K = world.B, actions.shape[0]
    pos, goal, heading = world.pos[:, 0], world.goal[:, 0], world.heading[:, 0]  # [B, 2]
    act = actions.unsqueeze(0).expand(B, K, 2)
    # World.step's operations: rotate into the world frame, clip the speed, move
    vel = world.clip_action(to_world(act, heading) if cfg.frame == "rotate" else act)
    active = world.outcome[:, :1] == RUNNING  # [B, 1]
    vel = vel * active.unsqueeze(-1)
    new_pos = advance(pos.unsqueeze(1), vel, cfg.dt)  # [B, K, 2]
    h0, _, valid0 = world.humans()
    h1, hv, hvalid = next_humans(world, model)
    swept = (segment_min_distance(h0.unsqueeze(1) - pos[:, None, None], h1.unsqueeze(1) - new_pos.unsqueeze(2))
             - world.radius_sum).masked_fill(~hvalid.unsqueeze(1), _FAR)  # [B, K, M]
    end = ((h1.unsqueeze(1) - new_pos.unsqueeze(2)).norm(dim=-1) - world.radius_sum).masked_fill(~hvalid.unsqueeze(1), _FAR)
    far = torch.full((B, K), _FAR)
    swept = swept.amin(-1) if world.Mh else far
    end = end.amin(-1) if world.Mh else far
    collision = active & (swept < 0)
    success = active & ~collision & ((goal.unsqueeze(1) - new_pos).norm(dim=-1) < cfg.robot_radius)
    timeout = active & ~collision & ~success & (world.steps + 1 >= cfg.time_limit).unsqueeze(-1)
    reward = step_reward(cfg, end, swept, success, collision, timeout, active)
    # V(s') reads the humans the robot senses now (the reward above is the world's: every human counts)
    seen = hvalid & valid0 & ((h0 - pos.unsqueeze(1)).norm(dim=-1) <= cfg.sensing_range)
    return {"robot_pos": new_pos, "robot_vel": vel, "humans_pos": h1, "humans_vel": hv, "humans_valid": seen,
            "reward": reward, "done": success | collision}


def lookahead_observation(world, actions: torch.Tensor, model: str) -> dict[str, torch.Tensor]:
    """:func:`candidates` in robot 0's observation frame (``rotate``: origin at the robot now, x towards its
    goal), as the observation's extra keys ``[B, 1, ...]``: ``cand_robot`` ``[K, 4]`` (next position,
    velocity), ``cand_reward``/``cand_done`` ``[K]``, ``cand_humans`` ``[M, 4]``, ``cand_humans_mask`` ``[M]`` and
    ``cand_running`` ``[]`` (the robot still acts)."""
    if world.cfg.frame != "rotate" or world.A != 1:
        raise ValueError("lookahead observations need one robot and frame=rotate")
    c = candidates(world, actions, model)
    pos, heading = world.pos[:, 0], world.heading[:, 0]
    rot = heading  # [B, 2]: to_local broadcasts it over the candidate / human axis
    robot = torch.cat((to_local(c["robot_pos"] - pos.unsqueeze(1), rot), to_local(c["robot_vel"], rot)), -1)
    humans = torch.cat((to_local(c["humans_pos"] - pos.unsqueeze(1), rot), to_local(c["humans_vel"], rot)), -1)
    humans = humans * c["humans_valid"].unsqueeze(-1)
    # cand_running: the robot still acts (a finished episode's action is ignored: the policy may skip it)
    return {"cand_robot": robot.unsqueeze(1), "cand_reward": c["reward"].unsqueeze(1), "cand_done": c["done"].unsqueeze(1),
            "cand_humans": humans.unsqueeze(1), "cand_humans_mask": c["humans_valid"].unsqueeze(1),
            "cand_running": world.outcome[:, :1] == RUNNING}


def placeholder_candidates(obs: dict, actions: torch.Tensor, dt: float) -> dict[str, torch.Tensor]:
    """Lookahead keys of the right shapes for an observation that has none (the harness's smoke test of a
    submission before any world exists): every action from the robot's origin, the humans held still."""
    robot, humans = obs["robot"], obs["humans"]
    B, K = robot.shape[0], actions.shape[0]
    moves = torch.cat((actions * dt, actions), -1).expand(B, 1, K, 4)
    return {"cand_robot": moves.clone(), "cand_reward": torch.zeros(B, 1, K), "cand_done": torch.zeros(B, 1, K, dtype=torch.bool),
            "cand_humans": humans.clone(), "cand_humans_mask": obs["humans_mask"].clone(),
            "cand_running": torch.ones(B, 1, dtype=torch.bool)}


def check_lookahead(model, actions, limit: int = 1024) -> tuple[str, torch.Tensor]:
    """A policy's declared lookahead, as a worker reports it: a known model and ``[K, 2]`` finite actions
    (``K <= limit``); ValueError otherwise."""
    if model not in MODELS:
        raise ValueError(f"lookahead model {str(model)[:40]!r} is not one of {', '.join(MODELS)}")
    acts = torch.as_tensor(actions, dtype=torch.float32)
    if acts.ndim != 2 or acts.shape[1] != 2 or not 1 <= acts.shape[0] <= limit or not torch.isfinite(acts).all():
        raise ValueError(f"lookahead actions must be [K, 2] finite with 1 <= K <= {limit}")
    return model, acts
