"""Actor and critic heads on top of any registered encoder (SPEC section 4).

- :class:`Actor`: encoder -> per-agent-node state ``robot_h`` -> MLP -> ``v_max * tanh``.
  Every agent is node 0 of its own graph, so one shared-weight MLP gives the action of
  every agent: ``[*, 6], [*, M, 4], [*, M] -> [*, 2]`` (``*`` = ``B, A``).
- :class:`Critic`: encoder -> ``robot_h`` concatenated with the action -> MLP -> ``Q [*, 1]``.
- :class:`TwinCritic`: two critics in one call (``torch.func`` vmap over the two parameter
  sets; the graph is built once) -> ``[2, *, 1]``. For hand-written TD3 loops; TorchRL's
  ``TD3Loss`` instead vmaps ONE :class:`Critic` over its own parameter copies
  (``num_qvalue_nets=2``), which every encoder supports (static shapes, no in-place
  writes to inputs, no ``.item()``).
- :func:`trace_for_inference`: a traced, frozen actor for fixed-shape deployment.
- :func:`actor_module` / :func:`critic_module`: ``TensorDictModule`` wrappers reading
  ``("agents", "observation", ...)`` (and ``("agents", "action")``) and writing
  ``("agents", "action")`` / ``("agents", "state_action_value")``.

Shared preprocessing (the fast path for training): graph construction is parameter-free
and, in a TD3 update, would otherwise run for the actor, both critics, the target actor
and both target critics. :func:`prepare_batch` computes it once per sampled batch (root
and ``"next"`` observations) under ``("agents", "observation", encoder.prep_key, field)``
and ``actor_module(actor, prepared=True)`` / ``critic_module(critic, prepared=True)`` read
those keys instead of the raw observation. The prepared modules share their parameters
with the raw ones (use the raw actor module in the collector)::

    policy = actor_module(actor)                       # acting: raw observations
    loss = TD3Loss(actor_module(actor, prepared=True), critic_module(critic, prepared=True), ...)
    batch = prepare_batch(replay_buffer.sample(), actor.encoder, critic.encoder)
    loss(batch)

The heads only use ``encoder.out_dim`` and ``robot_h``, never the encoder's internals, and ask
:func:`~crowdbench.models.encoder.splits` whether its preprocessing is split out.
"""

from __future__ import annotations

import copy
import itertools
import warnings

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from crowdbench.envs.observation import ACTION, GROUP, OBS
from crowdbench.kinematics import predict_observation
from crowdbench.models.encoder import RAW_FIELDS, forward_prepared, prep_fields, prepare, splits  # noqa: F401
from crowdbench.models.graph import unpack_obs
from crowdbench.models.vmap_once import once

OBS_KEYS = [OBS + ("robot",), OBS + ("humans",), OBS + ("humans_mask",)]
STATE_ACTION_VALUE = (GROUP, "state_action_value")
# an actor's base action for the observation (a residual on ORCA: algos/actors.py), computed once per collected
# transition and stored with it, so that the updates read it instead of running the base's solver per batch
BASE_ACTION = (GROUP, "base_action")


def mlp(sizes: list[int]) -> nn.Sequential:
    mods: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        mods.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            mods.append(nn.ReLU())
    return nn.Sequential(*mods)


class Actor(nn.Module):
    """Deterministic policy ``z = MLP(robot_h)`` squashed by tanh; ``hidden=None`` -> ``(out_dim,)``.

    ``squash="radial"`` (default): ``a = v_max * tanh(|z|) * z / |z|``, inside the speed disc.
    ``squash="box"``: ``a = v_max * tanh(z)`` per component. The simulator clips the speed to
    ``v_max``, so every box action beyond the disc acts like its radial projection: the critic
    sees no difference, the policy drifts into a corner where tanh saturates and its gradient
    vanishes. A 30-minute TD3 run with ``box`` froze at a ≈ (1, 1) (the robot spirals in at 45
    degrees to its goal); ``radial`` keeps every output meaningful.

    ``forward(robot [*, 6], humans [*, M, 4], humans_mask [*, M]) -> action [*, 2]`` (or a
    TensorDict holding the observation as the only argument).
    """

    def __init__(self, encoder: nn.Module, hidden: tuple | list | None = None, v_max: float = 1.0,
                 squash: str = "radial"):
        super().__init__()
        if squash not in ("radial", "box"):
            raise ValueError(f"unknown actor squash {squash!r}; valid: radial, box")
        self.encoder = encoder
        self.v_max = v_max
        self.squash = squash
        hidden = list(hidden) if hidden is not None else [encoder.out_dim]
        self.head = mlp([encoder.out_dim, *hidden, 2])

    extra_keys: tuple = ()  # inputs read after the observation, when present (a residual's BASE_ACTION)

    def act(self, robot_h: torch.Tensor) -> torch.Tensor:
        z = self.head(robot_h)
        if self.squash == "box":
            return self.v_max * torch.tanh(z)
        norm = z.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        return self.v_max * torch.tanh(norm) * (z / norm)

    def forward(self, robot, humans=None, humans_mask=None) -> torch.Tensor:
        _, h = self.encoder(*unpack_obs(robot, humans, humans_mask))
        return self.act(h)

    def forward_prepared(self, prep: dict) -> torch.Tensor:
        return self.act(forward_prepared(self.encoder, prep)[1])


# the critic's prediction is the shared kinematics' (crowdbench/kinematics.py), under the name it has always had here
lookahead = predict_observation


class Critic(nn.Module):
    """``Q(s, a) = MLP([robot_h(s), a])`` (the paper's critic); ``hidden=None`` -> ``(out_dim,)``.

    ``lookahead_dt > 0``: ``Q(s, a) = MLP([robot_h(s'(a)), a])`` where ``s'(a)`` is
    :func:`lookahead`'s prediction ``lookahead_dt`` seconds ahead (one step: the env's dt;
    longer: the robot holding ``a``), so the encoder sees where every human will be relative
    to the robot *after* the action. The features of ``(s'(a), a)`` determine those of
    ``(s, a)`` (a reparametrisation of the critic's input; only the graph's edges follow the
    predicted positions). Which action avoids whom becomes a question of geometry the
    encoder already answers, and ``dQ/da`` flows through it. Why an option:
    with the paper's critic, TD3 learns *when* a collision comes but not *which action*
    avoids it (docs/training.md). Cost: the critic's graph depends on the action, so it is
    built per call instead of once per batch (:func:`prepare_batch` serves the actor only).

    ``forward(robot [*, 6], humans [*, M, 4], humans_mask [*, M], action [*, 2]) -> Q [*, 1]``.
    """

    def __init__(self, encoder: nn.Module, hidden: tuple | list | None = None, lookahead_dt: float = 0.0,
                 v_max: float = 1.0):
        super().__init__()
        self.encoder = encoder
        self.lookahead_dt, self.v_max = float(lookahead_dt), float(v_max)
        hidden = list(hidden) if hidden is not None else [encoder.out_dim]
        self.head = mlp([encoder.out_dim + 2, *hidden, 1])

    def q(self, robot_h: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat((robot_h, action.to(robot_h.dtype)), -1))

    def forward(self, robot, humans, humans_mask, action) -> torch.Tensor:
        # the prediction and the encoder's preprocessing read no parameter: under TorchRL's vmapped
        # critics they run once for both copies (models/vmap_once.py)
        return self.q(forward_prepared(self.encoder, once(self._prepare, robot, humans, humans_mask, action))[1],
                      action)

    def _prepare(self, robot, humans, humans_mask, action) -> dict:
        if self.lookahead_dt > 0:
            robot, humans, humans_mask = lookahead(robot, humans, humans_mask, action, self.lookahead_dt, self.v_max)
        return prepare(self.encoder, robot, humans, humans_mask)

    def forward_prepared(self, prep: dict, action: torch.Tensor) -> torch.Tensor:
        if self.lookahead_dt > 0:
            raise ValueError("a lookahead critic builds its graph from the action: use critic_module(prepared=False)")
        return self.q(forward_prepared(self.encoder, prep)[1], action)


class TwinCritic(nn.Module):
    """Two independent critics (``critics[0]``, ``critics[1]``) evaluated in one batched call.

    ``forward(robot, humans, humans_mask, action) -> Q [2, *, 1]`` (or ``forward(td)`` with
    the observation and ``("agents", "action")``). The preprocessing (graph) is computed
    once for both; the parameters are stacked (differentiably) and the shared critic
    function is vmapped over them. ``vmap=False`` runs the two critics one after the other
    (same result; on the 2-core benchmark machine both take about the same time).
    """

    def __init__(self, critic: Critic, vmap: bool = True):
        super().__init__()
        second = copy.deepcopy(critic)
        for m in second.modules():  # independent initialisation
            if isinstance(m, nn.Linear | nn.RNNBase):
                m.reset_parameters()
        self.critics = nn.ModuleList([critic, second])
        self.vmap = vmap
        # stateless skeleton for functional calls (in a list: not a submodule)
        self._skeleton = [_Prepared(copy.deepcopy(critic), prep_fields(critic.encoder), True).to("meta")]

    def forward(self, robot, humans=None, humans_mask=None, action=None) -> torch.Tensor:
        if action is None:
            action = robot.get(ACTION)
        robot, humans, humans_mask = unpack_obs(robot, humans, humans_mask)
        prep = prepare(self.critics[0].encoder, robot, humans, humans_mask)
        if not self.vmap:
            return torch.stack([c.forward_prepared(prep, action) for c in self.critics])
        p0 = dict(self.critics[0].named_parameters())
        p1 = dict(self.critics[1].named_parameters())
        params = {"head." + n: torch.stack((p0[n], p1[n])) for n in p0}
        base = self._skeleton[0]
        args = (*[prep[f] for f in base.fields], action)
        return torch.vmap(lambda p: torch.func.functional_call(base, p, args))(params)

    def min_q(self, robot, humans=None, humans_mask=None, action=None) -> torch.Tensor:
        return self(robot, humans, humans_mask, action).min(0).values


class _Prepared(nn.Module):
    """Calls ``head.forward_prepared`` from positional prepared tensors (for TensorDictModule)."""

    def __init__(self, head: nn.Module, fields: tuple, with_action: bool):
        super().__init__()
        self.head = head
        self.fields = tuple(fields)
        self.with_action = with_action

    def forward(self, *tensors):
        if self.with_action:
            *tensors, action = tensors
            return self.head.forward_prepared(dict(zip(self.fields, tensors, strict=True)), action)
        # extra trailing inputs (actor_module's carry) are not the head's
        return self.head.forward_prepared(dict(zip(self.fields, tensors[: len(self.fields)], strict=True)))


def prepared_keys(encoder: nn.Module) -> list[tuple]:
    """``("agents", "observation", encoder.prep_key, field)`` for each prepared field (the
    raw observation keys for an encoder without the split, :mod:`crowdbench.models.encoder`)."""
    if not splits(encoder):
        return list(OBS_KEYS)
    return [OBS + (encoder.prep_key, f) for f in encoder.prep_fields]


def actor_module(actor: Actor, prepared: bool = False, carry: list | tuple = ()) -> TensorDictModule:
    """``TensorDictModule``: ``("agents", "observation", *)`` -> ``("agents", "action")``.

    ``prepared=True`` reads :func:`prepare_batch`'s keys instead (same parameters).
    ``carry`` keys are listed as (unused) inputs too: TorchRL's losses select the actor's ``in_keys``
    from the next state before calling the target critic, which a lookahead critic needs as raw
    observation (and a centralised critic as the scene)."""
    if prepared:
        fields = prep_fields(actor.encoder)
        mod = _Prepared(actor, fields, False)
        keys = prepared_keys(actor.encoder)
        keys = keys + [k for k in carry if k not in keys]
        return TensorDictModule(mod, in_keys=keys, out_keys=[ACTION])
    return TensorDictModule(actor, in_keys=[*OBS_KEYS, *actor.extra_keys], out_keys=[ACTION])


def critic_module(critic: Critic, prepared: bool = False) -> TensorDictModule:
    """``TensorDictModule``: observation + ``("agents", "action")`` -> ``("agents", "state_action_value")``.

    ``prepared=True`` reads :func:`prepare_batch`'s keys instead (same parameters); a lookahead
    critic always reads the raw observation (its graph depends on the action)."""
    if prepared and not getattr(critic, "lookahead_dt", 0):
        mod = _Prepared(critic, prep_fields(critic.encoder), True)
        keys = [*prepared_keys(critic.encoder), ACTION]
        return TensorDictModule(mod, in_keys=keys, out_keys=[STATE_ACTION_VALUE])
    return TensorDictModule(critic, in_keys=[*OBS_KEYS, ACTION], out_keys=[STATE_ACTION_VALUE])


def trace_for_inference(actor: Actor, robot, humans, humans_mask) -> torch.jit.ScriptModule:
    """The actor traced and frozen for fixed-shape inference (deployment, e.g. B = 1).

    The example observation fixes the shapes (leading dims and ``M``; other shapes give
    wrong results); the folded weights become constants and the decision runs without
    Python overhead (about 30-40% faster at B = 1 on the benchmark machine). Parameters are
    copied: re-trace after training. Gates are not recorded (use the eager actor for
    visualisation). Uses ``torch.jit.trace`` (deprecated in torch 2.x, still functional)."""
    actor = actor.eval()
    with torch.no_grad(), warnings.catch_warnings():
        # TorchScript is deprecated in favour of torch.compile, which gives no gain at B = 1
        # here (measured); shape-dependent Python branches are constants for fixed shapes.
        warnings.simplefilter("ignore", FutureWarning)
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        traced = torch.jit.trace(actor, (robot, humans, humans_mask), check_trace=False)
        return torch.jit.freeze(traced)


@torch.no_grad()
def prepare_batch(td, *encoders, include_next: bool = True, include_root: bool = True):
    """Add every distinct encoder preprocessing of ``td``'s observation (if ``include_root``) and of
    ``("next", ...)`` (if present and ``include_next``) under ``("agents", "observation", prep_key)``.
    Returns ``td`` (modified in place). ``include_root=False`` serves a TD3 critic-only step with
    a lookahead critic, which reads the actor's graphs of the next observation only."""
    roots = [()] if include_root else []
    if include_next and ("next",) + OBS + ("robot",) in td.keys(include_nested=True):
        roots.append(("next",))
    done = set()
    for enc in encoders:
        if not splits(enc):  # reads the raw observation
            continue
        if enc.prep_key in done:
            continue
        done.add(enc.prep_key)
        for root in roots:
            obs = td.get(root + OBS)
            prep = enc.prepare(obs.get("robot"), obs.get("humans"), obs.get("humans_mask"))
            for f, v in prep.items():
                td.set(root + OBS + (enc.prep_key, f), v)
    return td
