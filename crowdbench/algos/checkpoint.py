"""Checkpoints: state dicts + config only, written atomically, loaded with ``weights_only=True``."""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDict

from crowdbench.envs.observation import ACTION, Policy


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: the message names the file and the problem."""


REQUIRED = ("config", "actor", "frames")
# The checkpoint format: an integer stored under "format" in every checkpoint. Format 1 (crowdbench
# 0.1.0) wrote the string tag LEGACY_TAG instead; its configs may lack keys added since, which
# :func:`upgrade` fills with the values the format-1 code used. Bump FORMAT when a change to the
# saved fields or config needs an upgrade step, and add that step to UPGRADES.
FORMAT = 9
LEGACY_TAG = "crowdbench-checkpoint-v1"


def _upgrade_1(state: dict) -> dict:
    """Format 1 -> 2: defaults for config keys and fields that format-1 checkpoints may lack."""
    cfg = state["config"]
    algo, train = cfg.setdefault("algo", {}), cfg.setdefault("train", {})
    algo.setdefault("actor_squash", "box")  # the per-component tanh squash preceded the radial default
    algo.setdefault("per_weights", False)  # PER without importance-sampling weights, as in the paper
    look = algo.get("critic_lookahead", 0.0)
    if isinstance(look, bool):  # a flag for one env step before it became a horizon in seconds
        look = float(cfg.get("env", {}).get("dt", 0.25)) if look else 0.0
    algo["critic_lookahead"] = look
    algo.setdefault("exploration", "gaussian")
    algo.setdefault("ou_theta", 0.125)
    algo.setdefault("n_steps", 1)
    train.setdefault("progress_reward", 0.0)
    train.setdefault("human_dropout", 0.0)
    state.setdefault("wall_time_s", 0.0)
    if "torch_rng" in state and "replay_rng" not in state:
        # the replay sampler drew from an unseeded global RNG: continue from the seed's generator
        state["replay_rng"] = torch.Generator().manual_seed(int(cfg.get("seed", 0))).get_state()
    return state


def _upgrade_2(state: dict) -> dict:
    """Format 2 -> 3: ``env.humans`` (and ``env.reactive``) appeared with reactive replay; a replay run
    before it trained among the humans as recorded."""
    env = state["config"].setdefault("env", {})
    if env.get("name", "replay") == "replay":
        from crowdbench.envs.humans.reactive_replay import ReactiveParams

        env.setdefault("humans", "replay")
        env.setdefault("reactive", ReactiveParams().to_dict())
    return state


# the algo keys that algorithms did not read (their YAMLs carried every algorithm's keys before each
# got its own schema); format 4 configs hold an algorithm's own keys only
UNREAD_ALGO_KEYS = {
    "td3": ("lr_alpha", "alpha_init"),
    "ddpg": ("lr_alpha", "alpha_init", "policy_delay", "policy_noise", "noise_clip"),
    "sac": ("policy_delay", "policy_noise", "noise_clip", "exploration_sigma", "exploration", "ou_theta",
            "actor_squash"),
}


# the imitation warm start's keys (train.pretrain*, format 4) as a run before them trained: no warm start
PRETRAIN_DEFAULTS = {"pretrain": None, "pretrain_frames": 20000, "pretrain_epochs": 3, "pretrain_batch": 256,
                     "pretrain_lr": 1.0e-3, "pretrain_heldout": 0.1, "pretrain_bc_weight": 0.0,
                     "pretrain_bc_updates": 20000, "pretrain_checkpoint": None, "pretrain_dagger_rounds": 0,
                     "pretrain_dagger_frames": 5000}


def _upgrade_3(state: dict) -> dict:
    """Format 3 -> 4: drop the algo keys the algorithm never read; no imitation warm start."""
    cfg = state["config"]
    algo = cfg.get("algo", {})
    for key in UNREAD_ALGO_KEYS.get(algo.get("name"), ()):
        algo.pop(key, None)
    if "train" in cfg:
        for key, value in PRETRAIN_DEFAULTS.items():
            cfg["train"].setdefault(key, value)
    return state


def _upgrade_4(state: dict) -> dict:
    """Format 4 -> 5: ``encoder.compact`` (set encoders) and RGL's ``encoder.similarity`` / ``scale``
    appeared; a run before them trained uncompacted, RGL with the embedded-Gaussian similarity."""
    enc = state["config"].get("encoder", {})
    if enc.get("name") in ("sarl", "rgl", "dsrnn"):
        enc.setdefault("compact", False)
    if enc.get("name") == "rgl":
        enc.setdefault("similarity", "embedded_gaussian")
        enc.setdefault("scale", 5.0)
    return state


def _upgrade_5(state: dict) -> dict:
    """Format 5 -> 6: ``encoder.score_cap`` (sarl, gat, dsrnn) appeared; a run before it had the
    papers' unbounded attention scores."""
    enc = state["config"].get("encoder", {})
    if enc.get("name") in ("sarl", "gat", "dsrnn"):
        enc.setdefault("score_cap", None)
    return state


def _upgrade_6(state: dict) -> dict:
    """Format 6 -> 7: ``train.pretrain_checkpoint`` (the checkpoint expert) appeared; a run before it had none."""
    if "train" in state["config"]:
        state["config"]["train"].setdefault("pretrain_checkpoint", None)
    return state


def _upgrade_7(state: dict) -> dict:
    """Format 7 -> 8: DAgger (``train.pretrain_dagger_*``) and the self-play ``env.scale_geometry`` appeared;
    a run before them had no rounds and its square as configured."""
    cfg = state["config"]
    if "train" in cfg:
        for key in ("pretrain_dagger_rounds", "pretrain_dagger_frames"):
            cfg["train"].setdefault(key, PRETRAIN_DEFAULTS[key])
    if cfg.get("env", {}).get("name") == "selfplay":
        cfg["env"].setdefault("scale_geometry", False)
    return state


def _upgrade_8(state: dict) -> dict:
    """Format 8 -> 9: ``algo.actor_base`` and ``algo.actor_residual`` (a residual on ORCA) appeared for the
    off-policy algorithms; a run before them had a plain actor."""
    algo = state["config"].get("algo", {})
    if algo.get("name") in ("td3", "ddpg", "sac", "matd3"):
        algo.setdefault("actor_base", "none")
        algo.setdefault("actor_residual", 0.15)
    return state


UPGRADES = {1: _upgrade_1, 2: _upgrade_2, 3: _upgrade_3, 4: _upgrade_4, 5: _upgrade_5, 6: _upgrade_6,
            7: _upgrade_7, 8: _upgrade_8}  # format n -> n + 1


def upgrade(state: dict, version: int) -> dict:
    """A checkpoint of format ``version`` brought to :data:`FORMAT` (config defaults filled in)."""
    for v in range(version, FORMAT):
        state = UPGRADES[v](state)
    state["format"] = FORMAT
    return state


def checkpoint_format(state: dict, path: Path) -> int:
    """The format number of a loaded checkpoint: the integer tag, format 1 without one."""
    tag = state.get("format", 1)
    if tag == LEGACY_TAG:
        return 1
    if isinstance(tag, bool) or not isinstance(tag, int) or tag < 1:
        raise CheckpointError(f"not a crowdbench checkpoint: {path} (format tag {tag!r})")
    if tag > FORMAT:
        raise CheckpointError(f"checkpoint {path} has format {tag}, newer than this crowdbench reads "
                              f"(formats 1-{FORMAT}): upgrade crowdbench")
    return tag


def save_checkpoint(path: Path, state: dict) -> None:
    """Write to a temporary file, then rename: a kill mid-write never corrupts the last checkpoint; a
    full disk is an ``OSError`` naming the file (crowdbench/outputs.py)."""
    from crowdbench.outputs import save_torch_atomic

    save_torch_atomic(Path(path), {**state, "format": FORMAT})


def load_checkpoint(path: Path) -> dict:
    """A checkpoint's fields, upgraded to the current :data:`FORMAT` (see :func:`upgrade`)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for truncated zips, pickled code, garbage
        reason = " ".join(str(e).split())[:200]
        raise CheckpointError(f"corrupted or unsafe checkpoint {path}: {type(e).__name__}: {reason}") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"not a crowdbench checkpoint: {path} (not a dict of fields)")
    version = checkpoint_format(state, path)
    missing = [k for k in REQUIRED if k not in state]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks field(s): {', '.join(missing)}")
    if not isinstance(state["config"], dict):
        raise CheckpointError(f"checkpoint {path}: its config is not a mapping")
    return upgrade(state, version)


class LearnedPolicy(Policy):
    """A trained actor behind the evaluation :class:`Policy` interface (deterministic actions)."""

    def __init__(self, actor, name: str = "learned", frame: str = "rotate"):
        self.actor, self.name, self.frame = actor, name, frame

    @torch.no_grad()
    def act(self, td: TensorDict) -> torch.Tensor:
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return self.actor(td.clone(False))[ACTION]


def policy_from_checkpoint(path: Path) -> LearnedPolicy:
    """Rebuild the actor from a checkpoint's config and load its weights (shapes checked)."""
    from crowdbench.algos.actors import actor_base, build_actor

    state = load_checkpoint(path)
    cfg = state["config"]
    if cfg.get("algo", {}).get("name") == "value":  # a value network acting by lookahead (algos/value.py)
        from crowdbench.algos.value import policy_from_state

        try:
            return policy_from_state(state)
        except (KeyError, RuntimeError, ValueError, TypeError) as e:
            raise CheckpointError(f"checkpoint {path} does not fit its model: {' '.join(str(e).split())[:200]}") from None
    try:
        actor = build_actor(cfg["algo"]["name"], dict(cfg["encoder"]), cfg["env"]["v_max"],
                            squash=cfg["algo"].get("actor_squash", "radial"), base=actor_base(cfg),
                            residual=cfg["algo"].get("actor_residual"))
        actor.load_state_dict(state["actor"])
    except (KeyError, RuntimeError, ValueError, TypeError) as e:
        reason = " ".join(str(e).split())[:200]
        raise CheckpointError(f"checkpoint {path} does not fit its model: {reason}") from None
    actor.eval()
    name = f"{cfg['algo']['name']}-{cfg['encoder']['name']}"
    return LearnedPolicy(actor, name=name, frame=cfg["env"]["frame"])
