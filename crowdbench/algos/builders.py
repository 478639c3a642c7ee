"""Networks, TorchRL losses and exploration policies for TD3, DDPG and SAC.

Actor and critics are built from any registered encoder (each network owns its encoder
copy, as in the paper's Fig. 2); the losses are TorchRL's own modules with the keys of
the ``agents`` group.
"""

from __future__ import annotations

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import (
    AdditiveGaussianModule,
    OrnsteinUhlenbeckProcessModule,
    ProbabilisticActor,
    TanhNormal,
)
from torchrl.objectives import DDPGLoss, SACLoss, TD3Loss, ValueEstimators

from crowdbench.algos.nstep import STEPS
from crowdbench.envs.policy import ACTION, GROUP
from crowdbench.models import make_encoder
from crowdbench.models.graph import unpack_obs
from crowdbench.models.heads import (
    OBS_KEYS,
    STATE_ACTION_VALUE,
    Actor,
    Critic,
    actor_module,
    critic_module,
    mlp,
)

ALGOS = ("td3", "ddpg", "sac")
LOG_PROB = (GROUP, "action_log_prob")


class GaussianHead(nn.Module):
    """SAC's stochastic actor: encoder -> agent state -> MLP -> (loc, scale) of a TanhNormal."""

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
    """The policy network: deterministic (TD3, DDPG) or a TanhNormal ``ProbabilisticActor`` (SAC)."""
    if algo not in ALGOS:
        raise ValueError(f"unknown algo {algo!r}; valid: {', '.join(ALGOS)}")
    encoder = make_encoder(**encoder_cfg)
    if algo != "sac":
        return actor_module(Actor(encoder, hidden, v_max, squash))
    params = TensorDictModule(GaussianHead(encoder, hidden), in_keys=list(OBS_KEYS),
                              out_keys=[(GROUP, "loc"), (GROUP, "scale")])
    return ProbabilisticActor(
        params, in_keys={"loc": (GROUP, "loc"), "scale": (GROUP, "scale")}, out_keys=[ACTION],
        distribution_class=TanhNormal, distribution_kwargs={"low": -v_max, "high": v_max},
        return_log_prob=True, log_prob_key=LOG_PROB,
    )


def build_critic(encoder_cfg: dict, hidden=None, lookahead_dt: float = 0.0, v_max: float = 1.0) -> TensorDictModule:
    """Q network; ``lookahead_dt > 0``: the action-conditioned lookahead critic (models/heads.py Critic)."""
    return critic_module(Critic(make_encoder(**encoder_cfg), hidden, lookahead_dt, v_max))


def build_loss(algo: str, actor, critic, n_agents: int, v_max: float, a: dict, prepared: bool = False):
    """TorchRL loss with the ``agents`` keys and a TD(0) target (Algorithm 1, line 13).

    ``prepared=True`` (TD3, DDPG): the loss reads graphs that :func:`prepare_batch` built once
    per sampled batch instead of rebuilding them for the actor, both critics and the targets
    (six graph constructions per update otherwise). ``actor`` stays the raw-observation module
    for acting; the loss gets a prepared view sharing its parameters."""
    spec = leaf_action_spec(n_agents, v_max)
    # reads "priority_weight", shaped like the per-sample loss (Learner.update)
    weighted = bool(a["per_weights"])
    if prepared and algo != "sac":
        lookahead = getattr(critic.module, "lookahead_dt", 0) > 0  # its target needs the raw next observation
        actor = actor_module(actor.module, prepared=True, carry_raw=lookahead)
        critic = critic_module(critic.module, prepared=True)
    if algo == "td3":
        loss = TD3Loss(actor, critic, action_spec=spec, num_qvalue_nets=2, policy_noise=a["policy_noise"],
                       noise_clip=a["noise_clip"], loss_function=a["loss_function"], use_prioritized_weights=weighted)
    elif algo == "ddpg":
        loss = DDPGLoss(actor, critic, loss_function=a["loss_function"], delay_actor=True, delay_value=True,
                        use_prioritized_weights=weighted)
    else:
        loss = SACLoss(actor, critic, num_qvalue_nets=2, loss_function=a["loss_function"], action_spec=spec,
                       alpha_init=a["alpha_init"], target_entropy="auto", use_prioritized_weights=weighted)
    keys = {"reward": (GROUP, "reward"), "done": (GROUP, "done"), "terminated": (GROUP, "terminated"),
            "state_action_value": STATE_ACTION_VALUE}
    if algo != "ddpg":  # DDPGLoss takes the action key from the actor's out_keys
        keys["action"] = ACTION
    if algo == "sac":
        keys["log_prob"] = LOG_PROB
    loss.set_keys(**keys)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=a["gamma"])
    # n-step transitions (algos/nstep.py) carry their length m: the bootstrap is discounted by gamma^m
    loss.value_estimator.set_keys(steps_to_next_obs=STEPS)
    return loss


def exploration_policy(algo: str, actor, n_agents: int, v_max: float, sigma: float, noise: str = "gaussian",
                       theta: float = 0.125):
    """Algorithm 1, line 7: ``a = pi(G) + N(0, sigma)`` for TD3/DDPG; SAC samples its own policy.

    ``noise="ou"``: temporally correlated noise instead, TorchRL's Ornstein-Uhlenbeck module in
    steps (``x' = (1 - theta) x + s * N(0, 1)``, reset where the env's ``is_init`` is set, which
    needs an ``InitTracker``); ``s`` is chosen so that the stationary std is ``sigma``, the same
    scale as the Gaussian. Why: a lateral step of 0.25 m does not avoid anyone, a deviation held
    for ~1/theta steps (2 s at theta = 0.125) does."""
    if algo == "sac":
        return actor
    spec = leaf_action_spec(n_agents, v_max)
    if noise == "gaussian":
        module = AdditiveGaussianModule(spec=spec, sigma_init=sigma, sigma_end=sigma, action_key=ACTION, safe=True)
    elif noise == "ou":
        if not 0 < theta <= 1:
            raise ValueError(f"algo.ou_theta must be in (0, 1], got {theta}")
        module = OrnsteinUhlenbeckProcessModule(spec, eps_init=1.0, eps_end=1.0, theta=theta,
                                                sigma=sigma * (2 * theta - theta**2) ** 0.5, dt=1.0,
                                                action_key=ACTION, is_init_key="is_init", safe=True)
    else:
        raise ValueError(f"unknown algo.exploration {noise!r}; valid: gaussian, ou")
    return TensorDictSequential(actor, module)


def actor_parameters(loss) -> list[torch.Tensor]:
    return list(loss.actor_network_params.flatten_keys().values(True, True))


def critic_parameters(loss) -> list[torch.Tensor]:
    return list(loss.qvalue_network_params.flatten_keys().values(True, True)) if hasattr(
        loss, "qvalue_network_params") else list(loss.value_network_params.flatten_keys().values(True, True))
