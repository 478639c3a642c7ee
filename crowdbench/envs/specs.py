"""Specs and spaces of the observation layout (``crowdbench.envs.observation``), shared by every env.

The replay env and the self-play env expose the same agent group, and their PettingZoo
versions the same per-agent spaces; only the ``info`` entries differ.
"""

from __future__ import annotations

import numpy as np
import torch
from gymnasium import spaces
from torchrl.data import Bounded, Categorical, Composite, TensorSpec, Unbounded

from crowdbench.envs.observation import GROUP


def torchrl_specs(B: int, A: int, M: int, v_max: float, info: dict[str, TensorSpec]) -> dict[str, Composite]:
    """``observation_spec``, ``action_spec``, ``reward_spec`` and ``done_spec`` of ``B`` envs of
    ``A`` agents seeing ``M`` padded humans; ``info`` holds extra per-agent ``[B, A]`` entries."""
    agent_obs = Composite(
        observation=Composite(
            robot=Unbounded((B, A, 6)),
            humans=Unbounded((B, A, M, 4)),
            humans_mask=Categorical(2, (B, A, M), dtype=torch.bool),
            shape=(B, A),
        ),
        info=Composite(info, shape=(B, A)),
        shape=(B, A),
    )

    def flag(*shape):
        return Categorical(2, shape, dtype=torch.bool)

    return {
        "observation_spec": Composite({GROUP: agent_obs}, shape=(B,)),
        "action_spec": Composite({GROUP: Composite(action=Bounded(-v_max, v_max, (B, A, 2)), shape=(B, A))},
                                 shape=(B,)),
        "reward_spec": Composite({GROUP: Composite(reward=Unbounded((B, A, 1)), shape=(B, A))}, shape=(B,)),
        "done_spec": Composite(
            done=flag(B, 1), terminated=flag(B, 1), truncated=flag(B, 1),
            **{GROUP: Composite(done=flag(B, A, 1), terminated=flag(B, A, 1), truncated=flag(B, A, 1),
                                shape=(B, A))},
            shape=(B,),
        ),
    }


def gym_spaces(agents: list[str], M: int, v_max: float) -> tuple[dict, dict]:
    """Per-agent observation and action spaces for PettingZoo: one independent object per agent
    (each is seeded separately, and the API test checks that every call returns the same one)."""
    inf = np.float32(np.inf)

    def obs_space() -> spaces.Dict:
        return spaces.Dict({"robot": spaces.Box(-inf, inf, (6,), np.float32),
                            "humans": spaces.Box(-inf, inf, (M, 4), np.float32),
                            "humans_mask": spaces.Box(0.0, 1.0, (M,), np.float32)})

    return ({a: obs_space() for a in agents},
            {a: spaces.Box(-v_max, v_max, (2,), np.float32) for a in agents})
