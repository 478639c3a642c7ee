"""Training-only TorchRL transforms of the crowd env: progress shaping, human dropout and thinning.

Evaluation never uses them: the evaluation loop runs the bare env, so the paper's reward and
every human are what is reported.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from crowdbench.envs.observation import GROUP

_DIST = (GROUP, "info", "goal_dist")
_REWARD = (GROUP, "reward")


def _reset_mask(tensordict: TensorDictBase | None, batch: int) -> torch.Tensor:
    """The environments a reset call starts anew (as :class:`~crowdbench.envs.torchrl_env.CrowdEnv` reads it)."""
    if tensordict is not None and "_reset" in tensordict:
        return tensordict["_reset"].reshape(batch, -1).any(-1)
    return torch.ones(batch, dtype=torch.bool)


def density_keep(batch: int, n: int, p: float, gen: torch.Generator) -> torch.Tensor:
    """``[batch, n]`` slots kept: each row draws ``u ~ U(0, p)`` and drops each slot with probability ``u``
    (the density randomisation of :class:`HumanDropout` and of ``algo=value``'s ``algo.thin``)."""
    u = torch.rand(batch, 1, generator=gen) * p
    return torch.rand(batch, n, generator=gen) >= u


class ProgressReward(Transform):
    """Adds ``c * (d_before - d_after)`` per step, ``d`` the distance to the goal (``info/goal_dist``).

    It pays ``c`` per metre of progress, so stalling earns nothing (docs/training.md explains why
    CPU budgets need it); a finished agent does not move, so its shaping is exactly zero.
    """

    def __init__(self, coef: float):
        super().__init__(in_keys=[], out_keys=[])
        self.coef = float(coef)
        self._dist: torch.Tensor | None = None

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._dist = tensordict_reset.get(_DIST).clone()  # every env's distance now, reset or not
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        after = next_tensordict.get(_DIST)
        reward = next_tensordict.get(_REWARD)
        next_tensordict.set(_REWARD, reward + (self.coef * (self._dist - after)).unsqueeze(-1))
        self._dist = after.clone()
        return next_tensordict


class HumanDropout(Transform):
    """Density randomisation of the observation: each episode draws ``u ~ U(0, p)`` and hides each
    human slot with probability ``u`` for the whole episode.

    A hidden human is removed from what the policy sees (``humans_mask`` false, its row zero); it is
    still in the world, so it can still be hit and still counts in the danger term. A policy trained
    on the dense students001 thereby also sees sparse crowds (the evaluation scenes hotel and eth are
    sparse). Self-play agent slots are never hidden.
    """

    def __init__(self, p: float, seed: int, n_slots: int, n_humans: int):
        super().__init__(in_keys=[], out_keys=[])
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"train.human_dropout must be in [0, 1], got {p}")
        self.p, self.n_slots, self.n_humans = float(p), int(n_slots), int(n_humans)
        self.gen = torch.Generator().manual_seed(int(seed) + 7919)
        self.keep: torch.Tensor | None = None  # [B, S]

    def _hide(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get((GROUP, "observation"))
        keep = self.keep.unsqueeze(1)  # [B, 1, S]
        obs.set("humans_mask", obs.get("humans_mask") & keep)
        obs.set("humans", obs.get("humans") * keep.unsqueeze(-1))
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        B = tensordict_reset.batch_size[0]
        mask = _reset_mask(tensordict, B)
        drawn = density_keep(B, self.n_humans, self.p, self.gen)
        agents = torch.ones(B, self.n_slots - self.n_humans, dtype=torch.bool)
        keep = torch.cat((agents, drawn), 1)
        self.keep = keep if self.keep is None else torch.where(mask.view(-1, 1), keep, self.keep)
        return self._hide(tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._hide(next_tensordict)


class HumanThinning(Transform):
    """Density randomisation of the world: each episode draws ``u ~ U(0, p)`` and removes each recorded
    human with probability ``u`` for the whole episode: not seen, not hit, not in the danger term.

    Unlike :class:`HumanDropout` (the observation only), what the policy sees is then the crowd it moves
    in, so a residual on ORCA, whose base reads the observation, can still avoid everyone. The keep mask
    is drawn before the base env's reset (the first observation already lacks the removed humans) and
    only for the environments that start anew. Replay crowds only (``ReplayCrowd.keep``)."""

    def __init__(self, p: float, seed: int):
        super().__init__(in_keys=[], out_keys=[])
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"train.human_thinning must be in [0, 1], got {p}")
        self.p = float(p)
        self.gen = torch.Generator().manual_seed(int(seed) + 104729)

    def _reset_env_preprocess(self, tensordict: TensorDictBase | None) -> TensorDictBase | None:
        crowd = self.parent.base_env.world.crowd
        if not hasattr(crowd, "keep"):
            raise ValueError("train.human_thinning needs recorded humans (env=replay with env.humans=replay)")
        B, M = crowd.t.shape[0], crowd.M
        mask = _reset_mask(tensordict, B)
        drawn = density_keep(B, M, self.p, self.gen)
        crowd.keep = drawn if crowd.keep is None else torch.where(mask.view(-1, 1), drawn, crowd.keep)
        return super()._reset_env_preprocess(tensordict)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return tensordict_reset


SCENE = (GROUP, "state", "scene")
SCENE_MASK = (GROUP, "state", "scene_mask")


class SceneView(Transform):
    """Adds each agent's view of the whole scene (:meth:`~crowdbench.envs.world.World.scene_view`) under
    ``("agents", "state")``: what a centralised critic reads (``algo=mappo``) and no policy does.

    A transform rather than an env option: only a training env with a centralised critic pays for it,
    and evaluation (the bare env) can never hand it to a policy."""

    def __init__(self):
        super().__init__(in_keys=[], out_keys=[])

    def _world(self):
        return self.parent.base_env.world

    def _add(self, td: TensorDictBase) -> TensorDictBase:
        view = self._world().scene_view()
        td.set(SCENE, view["scene"])
        td.set(SCENE_MASK, view["scene_mask"])
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._add(tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._add(next_tensordict)

    def transform_observation_spec(self, observation_spec):
        from torchrl.data import Categorical, Composite, Unbounded

        w = self._world()
        B, A, N = w.B, w.A, w.M_all
        observation_spec[GROUP].set("state", Composite(scene=Unbounded((B, A, N, 7)),
                                                       scene_mask=Categorical(2, (B, A, N), dtype=torch.bool),
                                                       shape=(B, A)))
        return observation_spec
