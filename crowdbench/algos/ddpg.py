"""DDPG (Lillicrap et al. 2016): one critic, the actor and the targets updated every step; TorchRL's
``DDPGLoss`` with delayed (target) actor and value networks."""

from __future__ import annotations

from dataclasses import dataclass

from torchrl.objectives import DDPGLoss

from crowdbench.algos.offpolicy import NoisyActorConfig, OffPolicyAlgorithm
from crowdbench.config_fields import bounded


@dataclass
class DDPGConfig(NoisyActorConfig):
    """``algo=ddpg``."""

    name: str = bounded("ddpg", choices=("ddpg",))


class DDPG(OffPolicyAlgorithm):
    name = "ddpg"
    config = DDPGConfig

    def make_loss(self, actor, critic, action_spec):
        a = self.a
        return DDPGLoss(actor, critic, loss_function=a.loss_function, delay_actor=True, delay_value=True,
                        use_prioritized_weights=bool(a.per_weights))

    def extra_keys(self) -> dict:
        return {}  # DDPGLoss takes the action key from the actor's out_keys

    def critic_params(self):
        return self.loss.value_network_params

    def critic_loss(self, sample):
        return self.loss.loss_value(sample)

    def actor_loss(self, sample):
        return self.loss.loss_actor(sample)


ALGORITHM = DDPG
