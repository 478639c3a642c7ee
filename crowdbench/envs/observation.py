"""The observation TensorDict layout and the policy interface shared by baselines and learned policies.

Layout (batch ``[B]``, agent group ``agents`` with ``A`` agents, ``M`` padded humans)::

    ("agents", "observation", "robot")        [B, A, 6]     px, py, vx, vy, gx, gy
    ("agents", "observation", "humans")       [B, A, M, 4]  px, py, vx, vy (zero if unobserved)
    ("agents", "observation", "humans_mask")  [B, A, M]     observed (present and within 5 m)
    ("agents", "action")                      [B, A, 2]     vx, vy in the observation frame

Coordinates are in the robot frame named by the config (``rotate``: origin at the robot,
x-axis towards its goal). Actions are in the same frame; the simulator maps them back.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from tensordict import TensorDict

GROUP = "agents"
OBS = (GROUP, "observation")
ACTION = (GROUP, "action")


def obs_tensordict(obs: dict[str, torch.Tensor], batch_size: int) -> TensorDict:
    return TensorDict({GROUP: {"observation": obs}}, batch_size=[batch_size])


class Policy(ABC):
    """A controller evaluated on the protocol. ``act`` returns ``[B, A, 2]`` velocities."""

    #: observation/action frame this policy expects
    frame: str = "rotate"
    #: short name used in results files
    name: str = "policy"
    #: privileged policies (the oracle) see the simulator itself: :func:`crowdbench.protocols.replay.rollout`
    #: calls ``plan(sim)`` right after the reset, before the first ``act``. Their numbers are upper
    #: bounds, never comparable to a policy that only sees observations; results label them.
    privileged: bool = False

    def reset(self, mask: torch.Tensor) -> None:
        """Called with a ``[B]`` mask of environments that start a new episode."""

    @abstractmethod
    def act(self, td: TensorDict) -> torch.Tensor: ...
