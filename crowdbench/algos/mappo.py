"""MAPPO (Yu et al. 2022): PPO with one shared-weight actor for every agent and a centralised critic.

- ``algo=ippo`` (crowdbench/algos/ippo.py): each agent's critic reads its own observation (decentralised).
- ``algo=mappo``: a centralised critic, :class:`~crowdbench.models.scene_critic.SceneCritic`, reads the
  whole scene from each agent's frame: every body without a sensing range and the other agents' goals
  (``("agents", "state")``, added to the training env by :class:`~crowdbench.envs.transforms.SceneView`).
  The actor is the same decentralised graph policy, so evaluation and the harness see no difference.

GAE runs per agent over the collected ``[B, T, A]`` batch before the agents are flattened into
transitions (crowdbench/algos/ppo.py), with each agent's own episode cuts: an agent that finished is
done (sticky) until its environment resets, and its frozen steps are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tensordict.nn import TensorDictModule

from crowdbench.algos.ppo import KEEP, PPO, VALUE, PPOConfig
from crowdbench.config_fields import bounded
from crowdbench.envs.observation import GROUP, OBS
from crowdbench.envs.transforms import SCENE, SCENE_MASK, SceneView
from crowdbench.models.scene_critic import SceneCritic


@dataclass
class MAPPOConfig(PPOConfig):
    """``algo=mappo``."""

    name: str = bounded("mappo", choices=("mappo",))
    critic_dim: int = bounded(64, ge=1)  # the scene critic's per-body width
    critic_hidden: list[int] = field(default_factory=lambda: [128, 128], metadata={"ge": 1, "min_len": 1})  # its value MLP


class MAPPO(PPO):
    name = "mappo"
    config = MAPPOConfig
    keep = (*KEEP, (GROUP, "state"))

    @classmethod
    def env_transforms(cls, cfg) -> tuple:
        return (SceneView(),)

    def make_critic(self, cfg) -> TensorDictModule:
        net = SceneCritic(self.a.critic_dim, list(self.a.critic_hidden))
        return TensorDictModule(net, in_keys=[OBS + ("robot",), SCENE, SCENE_MASK], out_keys=[VALUE])


ALGORITHM = MAPPO
