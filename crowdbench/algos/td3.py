"""TD3 (Fujimoto et al. 2018), the paper's Algorithm 1: twin critics, delayed actor and target
updates, target policy smoothing; TorchRL's ``TD3Loss``."""

from __future__ import annotations

from dataclasses import dataclass

from torchrl.objectives import TD3Loss

from crowdbench.algos.actors import BASES
from crowdbench.algos.offpolicy import NoisyActorConfig, OffPolicyAlgorithm
from crowdbench.config_fields import bounded, rebound


@dataclass
class TD3Config(NoisyActorConfig):
    """``algo=td3``."""

    name: str = bounded("td3", choices=("td3",))
    policy_delay: int = bounded(2, ge=1)  # actor + targets every 2 critic updates (TD3's default)
    policy_noise: float = bounded(0.2, ge=0)  # target policy smoothing
    noise_clip: float = bounded(0.5, ge=0)
    actor_base: str = bounded("orca", choices=BASES)  # the default recipe: a residual on ORCA (algos/actors.py)
    # the default recipe's exploration noise (the previous default 0.3 and 0.15 did worse; docs/training.md)
    exploration_sigma: float = rebound(NoisyActorConfig, "exploration_sigma", 0.45)


class FirstCriticTD3Loss(TD3Loss):
    """``TD3Loss`` whose actor term evaluates critic 1 alone.

    Fujimoto et al.'s actor loss is ``-Q1(s, pi(s))``. TorchRL's ``TD3Loss.actor_loss`` runs both
    critics (vmapped over the stacked copies) and keeps ``[0]``: the second copy's forward and its
    all-zero backward are half the actor term's critic cost (for gatedgcn about a tenth of an update,
    benchmarks/profile_update.py). TorchRL has no option for it, hence this override. The loss and the
    actor's gradient are those of TorchRL's (same parameters, same reduction); only the critic-2 work
    that fed nothing is gone. The metadata keeps ``state_action_value_actor`` (critic 1's value)."""

    def actor_loss(self, tensordict):
        weights = self._maybe_get_priority_weight(tensordict)
        td = tensordict.select(*self.actor_network.in_keys, strict=False)
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            td = self.actor_network(td)
        td = td.select(*self.qvalue_network.in_keys, strict=False)
        with self._cached_detach_qvalue_network_params[0].to_module(self.qvalue_network,
                                                                   preserve_module_state=False):
            q1 = self.qvalue_network(td).get(self.tensor_keys.state_action_value).squeeze(-1)
        loss = self._reduce_loss(-q1, tensordict=tensordict, weights=weights)
        return loss, {"state_action_value_actor": q1.detach()}


class TD3(OffPolicyAlgorithm):
    name = "td3"
    config = TD3Config

    def __init__(self, cfg, n_agents: int):
        self.policy_delay = cfg.algo.policy_delay
        super().__init__(cfg, n_agents)

    def make_loss(self, actor, critic, action_spec):
        a = self.a
        return FirstCriticTD3Loss(actor, critic, action_spec=action_spec, num_qvalue_nets=2, policy_noise=a.policy_noise,
                       noise_clip=a.noise_clip, loss_function=a.loss_function,
                       use_prioritized_weights=bool(a.per_weights))


ALGORITHM = TD3
