"""MATD3 (Ackermann et al. 2019): TD3 with the shared-weight graph actor and centralised twin critics.

Each agent's ``Q(s, a_i)`` reads its view of the whole scene (every body with no sensing range and the other
agents' goals, :class:`~crowdbench.envs.transforms.SceneView`) and its own action
(:class:`~crowdbench.models.scene_critic.SceneQ`); the actor, the exploration and the update are TD3's
(crowdbench/algos/td3.py), so evaluation sees the same decentralised policy as every other entry. The replay
buffer keeps the scene views of each transition's state and next state.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tensordict.nn import TensorDictModule

from crowdbench.algos.actors import BASES
from crowdbench.algos.offpolicy import KEEP
from crowdbench.algos.td3 import TD3, TD3Config
from crowdbench.config_fields import bounded, rebound
from crowdbench.envs.observation import ACTION, GROUP, OBS
from crowdbench.envs.transforms import SCENE, SCENE_MASK, SceneView
from crowdbench.models.heads import STATE_ACTION_VALUE
from crowdbench.models.scene_critic import SceneQ


@dataclass
class MATD3Config(TD3Config):
    """``algo=matd3``."""

    name: str = bounded("matd3", choices=("matd3",))
    actor_base: str = bounded("none", choices=BASES)  # self-play rows: a plain actor (algos/actors.py)
    exploration_sigma: float = rebound(TD3Config, "exploration_sigma", 0.3)  # as the self-play rows trained
    critic_dim: int = bounded(64, ge=1)  # the scene critic's per-body width
    critic_hidden: list[int] = field(default_factory=lambda: [128, 128], metadata={"ge": 1, "min_len": 1})


class MATD3(TD3):
    name = "matd3"
    config = MATD3Config
    keep = (*KEEP, (GROUP, "state"), ("next", GROUP, "state"))

    @classmethod
    def env_transforms(cls, cfg) -> tuple:
        return (SceneView(),)

    def make_critic(self, cfg, horizon: float) -> TensorDictModule:
        net = SceneQ(self.a.critic_dim, list(self.a.critic_hidden))
        return TensorDictModule(net, in_keys=[OBS + ("robot",), SCENE, SCENE_MASK, ACTION],
                                out_keys=[STATE_ACTION_VALUE])

    def critic_reads_raw(self, horizon: float) -> bool:
        return True  # the scene view, never a prepared graph (algo.critic_lookahead is not read)


ALGORITHM = MATD3
