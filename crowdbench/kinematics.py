"""The kinematics the simulator and the networks share: speed clipping, frame rotations, motion at
constant velocity, and the one-step prediction of an observation under an action.

One module, below both (layer 0 of docs/architecture.md), so the world (crowdbench/envs/world.py), the
value lookahead's candidates (crowdbench/envs/lookahead.py), the lookahead critic
(crowdbench/models/heads.py) and the value networks' joint states (crowdbench/models/value_nets.py)
move and rotate with the same operations in the same order: the critic's prediction is the
simulator's step, not a re-implementation of it. Vectors are ``[..., 2]`` tensors; headings unit vectors.
"""

from __future__ import annotations

import torch


def into_disc(a: torch.Tensor, v_max: float) -> torch.Tensor:
    """``a`` scaled back onto the speed disc where its norm exceeds ``v_max``, unchanged inside it."""
    return a * (v_max / a.norm(dim=-1, keepdim=True).clamp_min(v_max))


def clip_speed(action: torch.Tensor, v_max: float) -> torch.Tensor:
    """Each component clamped to ``[-v_max, v_max]``, then the speed clipped to ``v_max`` (SPEC section 3)."""
    return into_disc(action.clamp(-v_max, v_max), v_max)


def advance(pos: torch.Tensor, vel: torch.Tensor, dt: float) -> torch.Tensor:
    """Where a body at ``pos`` moving at ``vel`` is ``dt`` seconds later (constant velocity)."""
    return pos + vel * dt


def to_local(vec: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """Rotate ``[..., K, 2]`` world vectors into the frame whose x-axis is ``heading`` ``[..., 2]``.

    Elementwise rather than ``vec @ R``: batched 2x2 matmuls cost ~20x more per call on CPU.
    """
    c, s = heading[..., 0:1], heading[..., 1:2]
    x, y = vec[..., 0], vec[..., 1]
    return torch.stack((c * x + s * y, c * y - s * x), -1)


def to_world(vec: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`to_local`: ``[..., K, 2]`` vectors of the ``heading`` frame in world axes."""
    c, s = heading[..., 0:1], heading[..., 1:2]
    x, y = vec[..., 0], vec[..., 1]
    return torch.stack((c * x - s * y, s * x + c * y), -1)


def heading_to(goal: torch.Tensor, pos: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """Unit vector from ``pos`` to ``goal``; at the goal the direction is undefined: keep ``heading``."""
    to_goal = goal - pos
    dist = to_goal.norm(dim=-1, keepdim=True)
    return torch.where(dist > 1e-6, to_goal / dist.clamp_min(1e-6), heading)


def predict_observation(robot, humans, humans_mask, action, dt: float, v_max: float):
    """The observation ``dt`` seconds ahead if the robot moves with ``action`` and every observed
    human keeps its velocity (robot-relative frame, axes kept): ``robot [*, 6]`` (``[px, py, vx, vy, gx,
    gy]``, crowdbench/envs/observation.py), ``humans [*, M, 4]`` (``[px, py, vx, vy]``), ``humans_mask [*, M]``.

    The robot stays at the origin with velocity ``a`` (:func:`clip_speed`, as the simulator clips it),
    the goal moves by ``-a dt`` and each human by ``(v_h - a) dt``; the mask is unchanged."""
    a = clip_speed(action.to(robot.dtype), v_max)
    shift = a * dt
    robot = torch.cat((robot[..., :2], a, robot[..., 4:6] - shift), -1)
    moved = advance(humans[..., :2], humans[..., 2:4], dt) - shift.unsqueeze(-2)
    humans = torch.cat((moved * humans_mask.unsqueeze(-1).to(humans.dtype), humans[..., 2:4]), -1)
    return robot, humans, humans_mask
