"""Imitation warm start (``train.pretrain=orca``): ORCA demonstrations, behaviour cloning, critic regression.

Before RL, :func:`collect_demonstrations` runs the ORCA baseline on the training env (the batched
env of ``train.py``, with its reward shaping) and returns per-agent transitions with the discounted
return-to-go of each agent episode. An algorithm's ``warm_start`` then calls :func:`imitate`:
the actor is fitted to ORCA's actions (:func:`behaviour_clone`) and each critic to the returns
(:func:`regress_values`), on the demonstrated episodes minus a held-out share on which the
imitation is measured. Off-policy algorithms also put the demonstrations into their replay buffer;
an on-policy one passes its state-value critic (``V(s) -> return``) to :func:`imitate` the same way.

Why the mode's squared error for a TanhNormal actor and not the demonstrations' negative
log-likelihood: ORCA is deterministic, so the NLL is unbounded (it is minimised by a vanishing
scale) and would leave SAC / PPO with no exploration; ~15 % of ORCA's action components sit on the
box boundary (full speed straight to the goal in the rotated frame), where ``atanh`` is infinite and a
clamped NLL is dominated by the clamp. The mode is also what an evaluation runs (a checkpoint acts
by its deterministic sample), so its error is the figure that matters, measured the same way for
deterministic and stochastic actors; the scale is left to RL (SAC's temperature, PPO's entropy).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase

from crowdbench.algos.multiagent import agent_transitions, finished_episodes
from crowdbench.algos.nstep import STEPS, n_step
from crowdbench.envs.observation import ACTION, GROUP, OBS
from crowdbench.envs.rules import SUCCESS
from crowdbench.models.heads import BASE_ACTION, OBS_KEYS

EXPERTS = ("orca", "checkpoint")
RETURN = (GROUP, "return_to_go")  # discounted, within the agent's episode, no bootstrap
COMPLETE = (GROUP, "episode_complete")  # the agent's episode ended before the collection did
EPISODE = (GROUP, "episode")  # an id per agent episode: the held-out split is by episode
LABEL = (GROUP, "expert_action")  # DAgger: the expert's action in a state the student visited
FIT_SAMPLE = 4096  # transitions the fit-set errors are measured on
TRANSITION = [OBS, ACTION, ("next", GROUP, "observation"), ("next", GROUP, "reward"), ("next", GROUP, "done"),
              ("next", GROUP, "terminated")]


def expert_policy(cfg, env=None):
    """The ``train.pretrain`` expert in the training env's observation frame: ORCA with the env's dynamics
    and the run's ``orca`` section (as ``policy=orca``), or the checkpoint ``train.pretrain_checkpoint``
    acting on ``env`` (crowdbench/algos/teacher.py)."""
    name = cfg.train.pretrain
    if name not in EXPERTS:
        raise ValueError(f"unknown train.pretrain {str(name)[:60]!r}; valid: {', '.join(EXPERTS)}")
    if name == "checkpoint":
        from crowdbench.algos.teacher import CheckpointExpert

        if not cfg.train.get("pretrain_checkpoint"):
            raise ValueError("train.pretrain=checkpoint needs train.pretrain_checkpoint=PATH")
        return CheckpointExpert(cfg.train.pretrain_checkpoint, env, cfg.env.frame, cfg.env.v_max)
    from crowdbench.baselines.orca import ORCA

    return ORCA.from_config(cfg)


def returns_to_go(reward: torch.Tensor, done: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``G_t = r_t + gamma (1 - done_t) G_{t+1}`` over ``[B, T, ...]`` (``done_t``: the step ends the
    episode), and whether the episode of step ``t`` ended within the ``T`` steps. An unfinished episode's
    ``G_t`` lacks its tail (no value to bootstrap from): :func:`imitate` fits no critic to those."""
    ret, complete = torch.zeros_like(reward), torch.zeros_like(done)
    g, ended = torch.zeros_like(reward[:, 0]), torch.zeros_like(done[:, 0])
    for t in reversed(range(reward.shape[1])):
        d = done[:, t]
        g = reward[:, t] + gamma * g * ~d
        ended = d | ended
        ret[:, t], complete[:, t] = g, ended
    return ret, complete


def episode_ids(done: torch.Tensor) -> torch.Tensor:
    """A distinct integer per (environment, agent, episode) of ``done`` ``[B, T, A, 1]``."""
    B, T = done.shape[:2]
    before = done.long().cumsum(1) - done.long()  # episodes ended before step t
    slot = torch.arange(B * math.prod(done.shape[2:])).view(B, 1, *done.shape[2:])
    return slot * (T + 1) + before


@torch.no_grad()
def collect_demonstrations(cfg, env, frames: int, expert=None) -> TensorDict:
    """``frames`` env steps (rounded up to whole batches of ``env.batch``) of ``expert`` (default: the
    ``train.pretrain`` one) on ``env``, as per-agent transitions (``agent_transitions``): the replay keys
    plus :data:`RETURN` (with ``cfg.algo.gamma``), :data:`COMPLETE` and :data:`EPISODE`; n-step
    transitions (with :data:`~crowdbench.algos.nstep.STEPS`) if ``cfg.algo.n_steps > 1``, as the
    replay buffer then holds. Advances ``env``'s episode sampler, as training would."""
    expert = expert_policy(cfg, env) if expert is None else expert

    def act(td):
        td.set(ACTION, expert.act(td.select(OBS)))
        return td

    steps = -(-int(frames) // int(env.batch_size[0]))
    batch = env.rollout(steps, act, break_when_any_done=False)
    nxt = batch["next", GROUP]
    gamma = float(cfg.algo.gamma)
    ret, complete = returns_to_go(nxt["reward"], nxt["done"], gamma)
    batch.set(RETURN, ret)
    batch.set(COMPLETE, complete)
    batch.set(EPISODE, episode_ids(nxt["done"]))
    keep = [*TRANSITION, RETURN, COMPLETE, EPISODE]
    if (GROUP, "state") in batch.keys(include_nested=True):  # a centralised critic's inputs (mappo, matd3)
        keep += [(GROUP, "state"), ("next", GROUP, "state")]
    n = int(cfg.algo.get("n_steps", 1))
    if n > 1:
        batch = n_step(batch, n, gamma)
        keep.append(STEPS)
    return agent_transitions(batch, keep)


def split_demos(demos: TensorDictBase, heldout: float, generator: torch.Generator):
    """``(fit, held)``: a random ``heldout`` share of the agent episodes is held out whole (neighbouring
    steps of one episode are nearly the same sample, a per-step split would measure recall)."""
    ids = demos[EPISODE].reshape(-1)
    uniq = ids.unique()
    n_held = round(heldout * len(uniq))
    if heldout > 0 and len(uniq) > 1:
        n_held = min(max(n_held, 1), len(uniq) - 1)
    held_ids = uniq[torch.randperm(len(uniq), generator=generator)[:n_held]]
    held = torch.isin(ids, held_ids)
    return demos[~held], demos[held]


def sample(td: TensorDictBase, n: int, generator: torch.Generator) -> TensorDictBase:
    """At most ``n`` random transitions of ``td``: the fit-set figures need no full pass over it."""
    return td if len(td) <= n else td[torch.randperm(len(td), generator=generator)[:n]]


def minibatches(n: int, size: int, epochs: int, generator: torch.Generator):
    for _ in range(epochs if n else 0):
        perm = torch.randperm(n, generator=generator)
        yield from perm.split(size)


def policy_action(actor, td: TensorDictBase, kind: str) -> torch.Tensor:
    """The action an evaluation would take (differentiable): a TanhNormal actor's deterministic sample."""
    obs = td.select(*OBS_KEYS, BASE_ACTION, strict=False)  # a residual's stored base velocity, where present
    if kind == "tanh_normal" and hasattr(actor, "get_dist"):
        return actor.get_dist(obs).deterministic_sample
    if kind == "tanh_normal":  # a residual on ORCA (algos/actors.py): its mode, through the base
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return actor(obs).get(ACTION)
    return actor(obs).get(ACTION)


@torch.no_grad()
def action_mse(actor, demos: TensorDictBase, kind: str, chunk: int = 2048) -> float:
    """Mean squared error per action component (m^2/s^2) of ``actor`` to the demonstrated actions."""
    if len(demos) == 0:  # (an empty TensorDict's numel() is 1)
        return float("nan")
    err = sum(F.mse_loss(policy_action(actor, part, kind), part[ACTION], reduction="sum").item()
              for part in demos.split(chunk))
    return err / demos[ACTION].numel()


def behaviour_clone(actor, fit: TensorDictBase, held: TensorDictBase, kind: str, *, epochs: int, batch: int,
                    lr: float, generator: torch.Generator, params=None) -> dict[str, float]:
    """Fit ``actor`` (``kind``: ``deterministic`` or ``tanh_normal``) to the demonstrated actions by the
    squared error of its evaluated action (module doc: why not the NLL). ``params``: what to optimise
    (default: all of ``actor``'s). A fresh Adam: the RL optimiser's moments stay untouched."""
    opt = torch.optim.Adam(list(actor.parameters()) if params is None else list(params), lr=lr)
    before = action_mse(actor, held, kind)
    for idx in minibatches(len(fit), batch, epochs, generator):
        mb = fit[idx]
        loss = F.mse_loss(policy_action(actor, mb, kind), mb[ACTION])
        opt.zero_grad()
        loss.backward()
        opt.step()
    return {"pretrain_action_mse": action_mse(actor, sample(fit, FIT_SAMPLE, generator), kind),
            "pretrain_heldout_action_mse_before": before,
            "pretrain_heldout_action_mse": action_mse(actor, held, kind)}


def _values(module, params, td: TensorDictBase, out_key, prepare) -> torch.Tensor:
    """``[K, n, ...]`` outputs of each of the ``K`` parameter sets stacked in ``params`` (one if unstacked)."""
    if prepare is not None:
        td = prepare(td.copy())
    stack = [params] if params.batch_dims == 0 else params.unbind(0)
    out = []
    for p in stack:
        with p.to_module(module):
            out.append(module(td.copy()).get(out_key))
    return torch.stack(out)


def _value_mse(module, params, td, out_key, prepare, chunk: int = 2048) -> float:
    if len(td) == 0:
        return float("nan")
    with torch.no_grad():
        err = sum(((_values(module, params, part, out_key, prepare) - part[RETURN]) ** 2).mean(0).sum().item()
                  for part in td.split(chunk))
    return err / td[RETURN].numel()


def regress_values(module, params, fit: TensorDictBase, held: TensorDictBase, out_key, *, epochs: int, batch: int,
                   lr: float, generator: torch.Generator, prepare=None, name: str = "critic") -> dict[str, float]:
    """Fit every critic of the functional ``params`` (TorchRL's ``*_network_params``: a vmapped twin
    stack ``[K]`` or a single set) run through ``module`` (the loss's parameter-free copy) so that
    ``out_key`` matches :data:`RETURN`: ``Q(s, a_demo)`` for a state-action critic, ``V(s)`` for a
    state-value one (the module reads what it needs from the transition). Only complete episodes count.
    ``prepare(td) -> td`` adds what the module reads beyond the raw observation (prepared graphs)."""
    fit, held = fit[fit[COMPLETE].reshape(-1)], held[held[COMPLETE].reshape(-1)]
    leaves = list(params.flatten_keys().values(True, True))
    opt = torch.optim.Adam(leaves, lr=lr)
    before = _value_mse(module, params, held, out_key, prepare)
    for idx in minibatches(len(fit), batch, epochs, generator):
        mb = fit[idx]
        # summed over the stack: each critic descends its own mean squared error, at full size
        loss = ((_values(module, params, mb, out_key, prepare) - mb[RETURN]) ** 2).flatten(1).mean(1).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return {f"pretrain_{name}_loss": _value_mse(module, params, sample(fit, FIT_SAMPLE, generator), out_key, prepare),
            f"pretrain_heldout_{name}_mse_before": before,
            f"pretrain_heldout_{name}_mse": _value_mse(module, params, held, out_key, prepare)}


def sync_targets(loss) -> None:
    """Copy every ``target_*_params`` of a TorchRL loss from its source: the targets would otherwise hold
    the untrained networks, and the first TD targets would undo the warm start at a rate ``tau``."""
    for name, target in loss.named_children():
        if name.startswith("target_") and name.endswith("_params"):
            target.data.update_(getattr(loss, name[len("target_"):]).data)


def imitate(cfg, actor, kind: str, demos: TensorDictBase, critics=(), prepare=None) -> dict[str, float]:
    """The warm start of any actor-critic: split, behaviour-clone ``actor``, regress each ``(module, params,
    out_key)`` of ``critics`` to the returns (``prepare``: see :func:`regress_values`). Returns the scalars
    to log. Seeded from ``cfg.seed`` with a generator of its own (the run's other streams are untouched)."""
    t = cfg.train
    generator = torch.Generator().manual_seed(int(cfg.seed))
    fit, held = split_demos(demos, float(t.pretrain_heldout), generator)
    opts = {"epochs": int(t.pretrain_epochs), "batch": int(t.pretrain_batch), "lr": float(t.pretrain_lr),
            "generator": generator}
    logs = {"pretrain_transitions": float(len(demos)), "pretrain_heldout_transitions": float(len(held))}
    logs.update(behaviour_clone(actor, fit, held, kind, **opts))
    for module, params, out_key in critics:
        logs.update(regress_values(module, params, fit, held, out_key, prepare=prepare, **opts))
    return logs


@torch.no_grad()
def collect_corrections(env, actor, kind: str, expert, frames: int) -> tuple[TensorDict, float]:
    """One DAgger round (Ross et al. 2011): ``frames`` env steps (whole batches) of the student ``actor``
    acting on ``env`` by its evaluated action, every visited state labelled with ``expert``'s action.
    Returns the labelled states as cloning data (:data:`OBS`, the label as :data:`ACTION`, :data:`EPISODE`)
    and the success rate of the student's episodes that ended in the round (nan if none did)."""

    def act(td):
        td.set(LABEL, expert.act(td.select(OBS)))  # the expert reads the world's current state: label first
        td.set(ACTION, policy_action(actor, td, kind))
        return td

    steps = -(-int(frames) // int(env.batch_size[0]))
    batch = env.rollout(steps, act, break_when_any_done=False)
    batch.set(EPISODE, episode_ids(batch["next", GROUP, "done"]))
    outcomes, _ = finished_episodes(batch, (GROUP, "reward"))
    success = sum(o == SUCCESS for o in outcomes) / len(outcomes) if outcomes else float("nan")
    data = agent_transitions(batch, [OBS, LABEL, EPISODE, ("next", GROUP, "done")])
    data.set(ACTION, data.pop(LABEL))
    return data.select(OBS, ACTION, EPISODE), success


def dagger(cfg, env, actor, kind: str, expert, demos: TensorDictBase) -> tuple[TensorDict, dict[str, float]]:
    """``train.pretrain_dagger_rounds`` rounds of :func:`collect_corrections` after the warm start's cloning:
    each round's labelled states join the data (the demonstrations first) and the actor is cloned again on
    all of it. Why: cloning alone fits the expert on the expert's states, and the student's small errors
    lead it into states no demonstration covers (measured: docs/value.md). Returns the aggregated data
    (what the cloning term of RL then draws from) and the scalars to log."""
    t = cfg.train
    generator = torch.Generator().manual_seed(int(cfg.seed) + 2)  # apart from imitate()'s stream
    data = demos.select(OBS, ACTION, EPISODE)
    logs = {}
    for r in range(int(t.pretrain_dagger_rounds)):
        new, success = collect_corrections(env, actor, kind, expert, int(t.pretrain_dagger_frames))
        offset = int(data[EPISODE].max()) + 1 if len(data) else 0  # keep the episode ids distinct
        new.set(EPISODE, new[EPISODE] + offset)
        logs[f"dagger_{r}_student_success"] = success
        logs[f"dagger_{r}_action_mse"] = action_mse(actor, new, kind)  # on the student's own states
        data = torch.cat([data, new])
        fit, held = split_demos(data, float(t.pretrain_heldout), generator)
        behaviour_clone(actor, fit, held, kind, epochs=int(t.pretrain_epochs), batch=int(t.pretrain_batch),
                        lr=float(t.pretrain_lr), generator=generator)
    logs["dagger_transitions"] = float(len(data))
    return data, logs


class DemoCloning:
    """``train.pretrain_bc_weight``: behaviour cloning kept in the actor loss during RL (TD3+BC's idea,
    Fujimoto & Gu 2021, applied to the demonstrations only): ``w(n) * |pi(s) - a_demo|^2`` on a minibatch
    of demonstrations at every actor step, with ``w`` decaying linearly to 0 over
    ``pretrain_bc_updates`` updates. Why: the critics are fitted at the demonstrated actions only, and
    the actor's first RL steps follow their extrapolated action gradient away from the imitation
    (docs/training.md); the term holds the actor near ORCA while the critics learn around it.

    The demonstrations are written once next to the checkpoint (``demos.pt``) so that a resumed run
    keeps the term; its sampling draws from a generator of its own, checkpointed with the run."""

    FILE = "demos.pt"

    def __init__(self, cfg, demos: TensorDictBase | None = None):
        t = cfg.train
        self.weight, self.horizon, self.batch = float(t.pretrain_bc_weight), int(t.pretrain_bc_updates), \
            int(cfg.algo.batch_size)
        self.demos = demos.select(*OBS_KEYS, BASE_ACTION, ACTION, strict=False) if demos is not None else None
        self.generator = torch.Generator().manual_seed(int(cfg.seed) + 1)

    def weight_at(self, updates: int) -> float:
        if self.horizon == 0:
            return self.weight
        return self.weight * max(0.0, 1.0 - updates / self.horizon)

    def loss(self, actor, kind: str, updates: int) -> torch.Tensor | None:
        w = self.weight_at(updates)
        if self.demos is None or w <= 0:
            return None
        idx = torch.randint(len(self.demos), (self.batch,), generator=self.generator)
        mb = self.demos[idx]
        return w * F.mse_loss(policy_action(actor, mb, kind), mb[ACTION])

    def save(self, out_dir) -> None:
        from pathlib import Path

        from crowdbench.outputs import save_torch_atomic

        path = Path(out_dir) / self.FILE
        if self.demos is not None and not path.exists():
            save_torch_atomic(path, {"demos": self.demos.to_dict(), "n": len(self.demos)})

    def restore(self, ckpt) -> None:
        from pathlib import Path

        from crowdbench.algos.checkpoint import CheckpointError

        path = Path(ckpt).parent / self.FILE
        try:
            saved = torch.load(path, map_location="cpu", weights_only=True)
            self.demos = TensorDict(saved["demos"], batch_size=[int(saved["n"])])
        except (OSError, KeyError, RuntimeError, TypeError) as e:
            raise CheckpointError(f"resume: train.pretrain_bc_weight > 0 needs the demonstrations {path} "
                                  f"({type(e).__name__}); pass train.pretrain_bc_weight=0 to continue without") from None
