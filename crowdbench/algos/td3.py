"""TD3 (Fujimoto et al. 2018), the paper's Algorithm 1: twin critics, delayed actor and target
updates, target policy smoothing; TorchRL's ``TD3Loss``."""

from __future__ import annotations

from dataclasses import dataclass

from torchrl.objectives import TD3Loss

from crowdbench.algos.offpolicy import NoisyActorConfig, OffPolicyAlgorithm
from crowdbench.schema_fields import bounded


@dataclass
class TD3Config(NoisyActorConfig):
    """``algo=td3``."""

    name: str = bounded("td3", choices=("td3",))
    policy_delay: int = bounded(2, ge=1)  # actor + targets every 2 critic updates (TD3's default)
    policy_noise: float = bounded(0.2, ge=0)  # target policy smoothing
    noise_clip: float = bounded(0.5, ge=0)


class TD3(OffPolicyAlgorithm):
    name = "td3"
    config = TD3Config

    def __init__(self, cfg, n_agents: int):
        self.policy_delay = cfg.algo.policy_delay
        super().__init__(cfg, n_agents)

    def make_loss(self, actor, critic, action_spec):
        a = self.a
        return TD3Loss(actor, critic, action_spec=action_spec, num_qvalue_nets=2, policy_noise=a.policy_noise,
                       noise_clip=a.noise_clip, loss_function=a.loss_function,
                       use_prioritized_weights=bool(a.per_weights))


ALGORITHM = TD3
