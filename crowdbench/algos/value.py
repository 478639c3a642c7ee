"""Value-based one-step lookahead (``algo=value``): CrowdNav's CADRL / LSTM-RL / SARL / LM-SARL algorithm
(Chen et al. 2019, ``crowd_nav/train.py``, ``utils/explorer.py``, ``utils/trainer.py``), batched.

A state-value network V(s) (:mod:`crowdbench.models.value_nets`) on the rotated joint state. Acting: for
every environment and each of the 81 holonomic actions, the candidate next state and its reward come with
the observation (:func:`crowdbench.envs.lookahead.lookahead_observation`, computed by the harness) and the
robot takes ``argmax_a r(s, a) + gamma^(dt v_pref) V(s'_a)``, all ``B x K`` candidates in one forward pass.
Training (:mod:`crowdbench.algos.value_train`): imitation of ORCA (V fitted to discounted returns), then
epsilon-greedy deep V-learning with a target network and a memory of ``(state, target)`` pairs.

This module holds the config, the value of the candidates and the greedy policy (what evaluation loads).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict

from crowdbench.config_fields import bounded
from crowdbench.envs.lookahead import MODELS, PRIVILEGED_MODELS, action_set
from crowdbench.envs.observation import OBS, Policy
from crowdbench.models.value_nets import NETS, build_value_net, net_input


@dataclass
class ValueConfig:
    """``algo=value`` (crowdbench/conf/algo/value.yaml); defaults are CrowdNav's ``train.config`` / ``policy.config``."""

    name: str = bounded("value", choices=("value",))
    net: str = bounded("sarl", choices=NETS)  # encoder: the run's encoder group (encoder=gatedgcn, ...) as V
    lookahead: str = bounded("query", choices=MODELS)  # query: PRIVILEGED (the simulator's next human states)
    kinematics: str = bounded("holonomic", choices=("holonomic", "unicycle"))
    speeds: int = bounded(5, ge=1)
    headings: int = bounded(16, ge=1)
    gamma: float = bounded(0.9, gt=0, le=1)  # discounted per dt * v_pref (gamma^(0.25) per step)
    terminal_value: bool = True  # CrowdNav adds gamma V(s') even where s' ends the episode; false: r only
    batch: int = bounded(32, ge=1)  # environments run together (episodes per round)
    # imitation (train.config [imitation_learning])
    il_episodes: int = bounded(3000, ge=0)
    il_epochs: int = bounded(50, ge=0)
    il_lr: float = bounded(0.01, gt=0)
    il_optimizer: str = bounded("sgd", choices=("sgd", "adam"))
    il_steps: int = bounded(0, ge=0)  # gradient steps of the fit; 0: il_epochs epochs over the memory (CrowdNav)
    il_safety_space: float = bounded(0.15, ge=0)  # m added to the demonstrator ORCA's human radius
    # deep V-learning (train.config [train])
    episodes: int = bounded(10000, ge=0)
    lr: float = bounded(0.001, gt=0)
    optimizer: str = bounded("sgd", choices=("sgd", "adam"))  # sgd: CrowdNav's SGD with momentum 0.9
    train_batches: float = bounded(100.0, ge=0)  # gradient steps per finished episode
    batch_size: int = bounded(100, ge=1)
    capacity: int = bounded(100000, ge=1)
    thin: float = bounded(0.0, ge=0, le=1)  # training-only: each episode removes each recorded human w.p. u ~ U(0, thin)
    store_timeouts: bool = False  # true: also learn from timed-out episodes (bootstrapped; not CrowdNav's)
    target_update: int = bounded(50, ge=1)  # episodes between target-network refreshes
    epsilon_start: float = bounded(0.5, ge=0, le=1)
    epsilon_end: float = bounded(0.1, ge=0, le=1)
    epsilon_decay: int = bounded(4000, ge=1)  # episodes
    val_every: int = bounded(1000, ge=0)  # episodes between validations on the 100 validation cases (0: none)
    keep_best: bool = False  # true: keep the network of the best validation (imitation's included), not the last
    max_minutes: float = bounded(0.0, ge=0)  # wall-time budget of the RL phase (0: none)


CHUNK = 16  # environments per forward pass of the candidates where slots go unsensed (candidate_values)
VALUE_KEYS = ("robot", "cand_robot", "cand_humans", "cand_humans_mask", "cand_reward", "cand_done")


def epsilon(episode: torch.Tensor, start: float, end: float, decay: int) -> torch.Tensor:
    """CrowdNav's schedule: linear from ``start`` to ``end`` over ``decay`` episodes, then ``end``."""
    frac = episode.to(torch.float64).clamp(max=decay) / decay
    return start + (end - start) * frac


def gamma_bar(gamma: float, dt: float, v_pref: float) -> float:
    """The per-step discount: CrowdNav discounts by ``gamma ** (dt * v_pref)``."""
    return gamma ** (dt * v_pref)


class ValueModel:
    """A value network with what it needs to read observations: the action set, radii, ``v_pref``, discount."""

    def __init__(self, a, env_cfg, encoder_cfg: dict | None = None):
        self.net_name, self.lookahead = str(a.net), str(a.lookahead)
        self.v_pref, self.dt = float(env_cfg.v_max), float(env_cfg.dt)
        self.radii = (float(env_cfg.robot_radius), float(env_cfg.human_radius))
        self.actions = action_set(self.v_pref, int(a.speeds), int(a.headings), str(a.kinematics))
        self.gamma_bar = gamma_bar(float(a.gamma), self.dt, self.v_pref)
        self.terminal_value = bool(a.terminal_value)
        self.net = build_value_net(self.net_name, encoder_cfg)
        self.label = encoder_cfg["name"] if self.net_name == "encoder" else self.net_name  # for results

    def state(self, obs) -> tuple[torch.Tensor, torch.Tensor]:
        """``(input [B, M, D], mask [B, M])`` of the current state from observations ``robot [B, 1, 6]``,
        ``humans [B, 1, M, 4]``, ``humans_mask`` (rotate frame: the robot at the origin)."""
        robot, humans, mask = obs["robot"][:, 0], obs["humans"][:, 0], obs["humans_mask"][:, 0]
        x = net_input(self.net_name, robot[:, 0:2], robot[:, 2:4], robot[:, 4:6], humans[..., 0:2], humans[..., 2:4],
                      mask, self.radii, self.v_pref)
        return x, mask

    def candidate_values(self, obs, net=None) -> torch.Tensor:
        """``[B, K]``: ``r(s, a) + gamma_bar V(s'_a)`` of every candidate, one forward pass for all ``B x K``; where
        some slot goes unsensed (a replayed scene), :data:`CHUNK` environments per pass, the environments taken
        by the number of humans they sense: each pass then drops the slots its environments leave empty
        (:func:`~crowdbench.models.value_nets.compact`), and a batch of 250 evaluation episodes does not pay
        for its densest one in every row. Where every slot is sensed (CrowdNav) it is one pass, as before."""
        mask = obs["cand_humans_mask"][:, 0]
        if mask.shape[0] <= CHUNK or mask.all():
            return self._values(obs, net)
        order = torch.argsort(mask.sum(-1), stable=True)
        out = torch.empty(mask.shape[0], self.actions.shape[0])
        for i in range(0, len(order), CHUNK):
            rows = order[i:i + CHUNK]
            out[rows] = self._values({k: obs[k][rows] for k in VALUE_KEYS}, net)
        return out

    def _values(self, obs, net=None) -> torch.Tensor:
        net = self.net if net is None else net
        robot, cr, ch = obs["robot"][:, 0], obs["cand_robot"][:, 0], obs["cand_humans"][:, 0]
        mask = obs["cand_humans_mask"][:, 0]  # [B, M]
        B, K, M = cr.shape[0], cr.shape[1], ch.shape[1]
        x = net_input(self.net_name, cr[..., 0:2], cr[..., 2:4], robot[:, None, 4:6], ch[:, None, :, 0:2],
                      ch[:, None, :, 2:4], mask.unsqueeze(1), self.radii, self.v_pref)  # [B, K, M, D]
        v = net(x.reshape(B * K, M, -1), mask.unsqueeze(1).expand(B, K, M).reshape(B * K, M)).reshape(B, K)
        if not self.terminal_value:
            v = torch.where(obs["cand_done"][:, 0], 0.0, v)
        return obs["cand_reward"][:, 0] + self.gamma_bar * v

    def greedy(self, obs) -> torch.Tensor:
        """``[B]`` index of the best candidate (the first of equal values: deterministic)."""
        return self.candidate_values(obs).argmax(-1)


class ValuePolicy(Policy):
    """The greedy lookahead policy behind the evaluation interface. ``lookahead`` tells the harness which
    candidates to hand over (:func:`crowdbench.envs.lookahead.lookahead_observation`); with ``query`` the
    entry is privileged (labelled so in results; it is not the oracle's plan-ahead, so ``privileged`` stays
    False and ``privileged_lookahead`` says it)."""

    frame = "rotate"

    def __init__(self, model: ValueModel, name: str | None = None):
        self.model = model
        self.model.net.eval()
        self.lookahead = (model.lookahead, model.actions)
        self.privileged_lookahead = model.lookahead in PRIVILEGED_MODELS
        tag = " (privileged)" if self.privileged_lookahead else ""
        self.name = name or f"value-{model.label}-{model.lookahead}{tag}"

    @torch.no_grad()
    def act(self, td: TensorDict) -> torch.Tensor:
        obs = td[OBS]
        best = torch.zeros(obs["robot"].shape[0], dtype=torch.long)  # stop where the episode has ended
        rows = obs["cand_running"][:, 0].nonzero().squeeze(-1)  # only these: finished episodes ignore actions
        if len(rows):
            best[rows] = self.model.greedy(obs[rows])
        return self.model.actions[best].unsqueeze(1)  # [B, 1, 2]


def policy_from_state(state: dict) -> ValuePolicy:
    """The greedy policy of an ``algo=value`` checkpoint (``config``; ``actor``: the value network's weights)."""
    from types import SimpleNamespace

    cfg = state["config"]
    model = ValueModel(SimpleNamespace(**cfg["algo"]), SimpleNamespace(**cfg["env"]), cfg.get("encoder"))
    model.net.load_state_dict(state["actor"])
    return ValuePolicy(model)


class Value:
    """The registry's component (crowdbench/algos/registry.py): the schema and the actor kind. Training is
    :func:`crowdbench.algos.value_train.train_value` (not the collector loop of crowdbench/algos/train.py:
    acting needs the lookahead candidates of the world, and episodes end before their targets are known)."""

    name = "value"
    config = ValueConfig
    actor_kind = "value"


ALGORITHM = Value
