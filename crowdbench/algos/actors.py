"""The acting networks, built from a registered algorithm's actor kind and any registered encoder.

This is all an evaluation needs of an algorithm (the checkpoint loader builds the actor from
here and the registry's actor kind); losses, critics and updates live in the algorithm modules.
"""

from __future__ import annotations

from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import ProbabilisticActor, TanhNormal

from crowdbench.algos.registry import actor_kind
from crowdbench.envs.policy import ACTION, GROUP
from crowdbench.models import make_encoder
from crowdbench.models.graph import unpack_obs
from crowdbench.models.heads import OBS_KEYS, Actor, actor_module, mlp

LOG_PROB = (GROUP, "action_log_prob")


class GaussianHead(nn.Module):
    """A stochastic actor: encoder -> agent state -> MLP -> (loc, scale) of a TanhNormal."""

    def __init__(self, encoder: nn.Module, hidden: list | None = None):
        super().__init__()
        self.encoder = encoder
        hidden = list(hidden) if hidden is not None else [encoder.out_dim]
        self.head = nn.Sequential(mlp([encoder.out_dim, *hidden, 4]), NormalParamExtractor())

    def forward(self, robot, humans=None, humans_mask=None):
        _, h = self.encoder(*unpack_obs(robot, humans, humans_mask))
        return self.head(h)


def leaf_action_spec(n_agents: int, v_max: float) -> Bounded:
    return Bounded(-v_max, v_max, (n_agents, 2))


def build_actor(algo: str, encoder_cfg: dict, v_max: float, hidden=None, squash: str = "radial") -> TensorDictModule:
    """Algorithm ``algo``'s policy network: deterministic (``squash``: models/heads.py Actor) or a
    TanhNormal ``ProbabilisticActor`` that acts by its mode under deterministic exploration."""
    kind = actor_kind(algo)
    encoder = make_encoder(**encoder_cfg)
    if kind == "deterministic":
        return actor_module(Actor(encoder, hidden, v_max, squash))
    params = TensorDictModule(GaussianHead(encoder, hidden), in_keys=list(OBS_KEYS),
                              out_keys=[(GROUP, "loc"), (GROUP, "scale")])
    return ProbabilisticActor(
        params, in_keys={"loc": (GROUP, "loc"), "scale": (GROUP, "scale")}, out_keys=[ACTION],
        distribution_class=TanhNormal, distribution_kwargs={"low": -v_max, "high": v_max},
        return_log_prob=True, log_prob_key=LOG_PROB,
    )
