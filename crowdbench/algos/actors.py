"""The acting networks, built from a registered algorithm's actor kind and any registered encoder.

This is all an evaluation needs of an algorithm (the checkpoint loader builds the actor from
here and the registry's actor kind); losses, critics and updates live in the algorithm modules.
"""

from __future__ import annotations

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import ProbabilisticActor, TanhNormal

from crowdbench.algos.registry import actor_kind
from crowdbench.envs.observation import ACTION, GROUP
from crowdbench.kinematics import into_disc
from crowdbench.models import make_encoder
from crowdbench.models.graph import unpack_obs
from crowdbench.models.heads import BASE_ACTION, OBS_KEYS, Actor, actor_module, mlp

LOG_PROB = (GROUP, "action_log_prob")
RESIDUAL = (GROUP, "residual")  # a stochastic residual actor's sample, the key its log-probability is of
BASES = ("none", "orca")  # algo.actor_base


class OrcaResidual(Actor):
    """``a = P(ORCA(s) + r(s))``: a learned residual on top of ORCA's velocity (``algo.actor_base=orca``).

    ``r`` is :class:`~crowdbench.models.heads.Actor`'s squashed head scaled to at most ``scale`` m/s
    (``algo.actor_residual``; default ``v_max``), its last layer zeroed so that the untrained actor *is*
    ORCA; ``P`` scales the sum back into the speed disc. ORCA is
    computed from the observation alone (the ORCA baseline's solver and parameters, ``baselines/orca.py``),
    so nothing is privileged. Why: a cloned actor imitates ORCA to a held-out action error of 0.013 and still
    drives at 0.53-0.55 on protocol v1 against ORCA's 0.935 (the errors compound over an episode;
    docs/training.md), while the residual starts exactly at ORCA and RL only has to learn the corrections.
    The base carries no gradient: the actor's gradient reaches the residual only."""

    def __init__(self, encoder: nn.Module, hidden, v_max: float, squash: str, base, scale: float | None = None):
        super().__init__(encoder, hidden, v_max, squash)
        self.base = [base]  # in a list: a solver, not a submodule (no parameters, not in the state dict)
        self.scale = float(v_max if scale is None else scale)  # the residual's largest speed (m/s)
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    extra_keys = (BASE_ACTION,)

    def forward(self, robot, humans=None, humans_mask=None, base=None) -> torch.Tensor:
        """``base``: ORCA's velocity for this observation if already computed (:meth:`store_base`), else computed."""
        robot, humans, humans_mask = unpack_obs(robot, humans, humans_mask)
        _, h = self.encoder(robot, humans, humans_mask)
        if base is None:
            base = self.base[0].velocities(robot, humans, humans_mask)
        a = base.to(h.dtype) + self.act(h) * (self.scale / self.v_max)
        return into_disc(a, self.v_max)

    def store_base(self, td):
        """Sets :data:`BASE_ACTION` (and ``("next", *BASE_ACTION)``) of ``td``'s observations in place.

        ORCA's solver runs per observation, so a velocity computed here for a batch of collected transitions
        is bit for bit the one the forward pass computes for the same observation in any sampled batch:
        the updates read it instead of running the solver for the actor term, the target actor and the
        cloning term (about 1,600 observations per collection step of 16 environments, against 32 here)."""
        for pre in ((), ("next",)):
            if (*pre, *OBS_KEYS[0]) in td.keys(True):
                obs = [td.get((*pre, *k)) for k in OBS_KEYS]
                td.set((*pre, *BASE_ACTION), self.base[0].velocities(*obs))
        return td

    def forward_prepared(self, prep: dict) -> torch.Tensor:
        raise ValueError("an actor on an ORCA base reads the raw observation (ORCA needs it): use actor_module(prepared=False)")


def actor_base(cfg):
    """``algo.actor_base`` of a composed config (DictConfig or dict): the ORCA policy the actor adds its
    residual to, built as ``policy=orca`` is (the run's ``orca`` section, env dynamics and seed), or None."""
    name = (cfg["algo"].get("actor_base") or "none")
    if name not in BASES:
        raise ValueError(f"unknown algo.actor_base {str(name)[:60]!r}; valid: {', '.join(BASES)}")
    if name == "none":
        return None
    from crowdbench.baselines.orca import ORCA

    return ORCA.from_config(cfg)


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


class ResidualAction(nn.Module):
    """``a = P(ORCA(s) + r)`` for a sampled residual ``r`` (a stochastic actor on an ORCA base): the same base and
    projection as :class:`OrcaResidual`, after the distribution instead of inside the network."""

    def __init__(self, base, v_max: float):
        super().__init__()
        self.base, self.v_max = [base], float(v_max)  # in a list: a solver, not a submodule

    def forward(self, robot, humans, humans_mask, residual):
        base = self.base[0].velocities(*unpack_obs(robot, humans, humans_mask))
        a = base.to(residual.dtype) + residual
        return into_disc(a, self.v_max)


def residual_distribution(actor: TensorDictSequential):
    """The probabilistic part of a stochastic residual actor (what PPO's loss evaluates), else ``actor``."""
    return actor[0] if isinstance(actor, TensorDictSequential) and RESIDUAL in actor[0].out_keys else actor


def leaf_action_spec(n_agents: int, v_max: float) -> Bounded:
    return Bounded(-v_max, v_max, (n_agents, 2))


def build_actor(algo: str, encoder_cfg: dict, v_max: float, hidden=None, squash: str = "radial",
                base=None, residual: float | None = None) -> TensorDictModule:
    """Algorithm ``algo``'s policy network: deterministic (``squash``: models/heads.py Actor; a residual on
    ``base``'s velocity if given: :class:`OrcaResidual`) or a TanhNormal ``ProbabilisticActor`` that acts by
    its mode under deterministic exploration (on a ``base``: a TanhNormal residual of at most ``residual`` m/s
    per component, sampled into :data:`RESIDUAL`, then :class:`ResidualAction` writes the action)."""
    kind = actor_kind(algo)
    encoder = make_encoder(**encoder_cfg)
    if kind == "deterministic":
        return actor_module(Actor(encoder, hidden, v_max, squash) if base is None
                            else OrcaResidual(encoder, hidden, v_max, squash, base, residual))
    if base is not None and kind != "tanh_normal":
        raise ValueError(f"algo.actor_base needs a deterministic or a TanhNormal actor; {algo}'s is {kind}")
    head = GaussianHead(encoder, hidden)
    # on an ORCA base the distribution is over the residual, at most `residual` m/s per component; its mean
    # starts at zero (the last layer zeroed), so the untrained actor's deterministic action is ORCA's
    bound = v_max if base is None else float(v_max if residual is None else residual)
    if base is not None:
        nn.init.zeros_(head.head[0][-1].weight)
        nn.init.zeros_(head.head[0][-1].bias)
    params = TensorDictModule(head, in_keys=list(OBS_KEYS), out_keys=[(GROUP, "loc"), (GROUP, "scale")])
    dist = ProbabilisticActor(
        params, in_keys={"loc": (GROUP, "loc"), "scale": (GROUP, "scale")},
        out_keys=[ACTION if base is None else RESIDUAL],
        distribution_class=TanhNormal, distribution_kwargs={"low": -bound, "high": bound},
        return_log_prob=True, log_prob_key=LOG_PROB,
    )
    if base is None:
        return dist
    return TensorDictSequential(dist, TensorDictModule(ResidualAction(base, v_max), in_keys=[*OBS_KEYS, RESIDUAL],
                                                       out_keys=[ACTION]))
