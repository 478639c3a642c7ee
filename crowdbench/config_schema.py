"""Typed, bounded schemas of the ``crowdbench`` config (``crowdbench/conf/``), one dataclass per group.

Every key of every shipped YAML has a field here, with its type and, where a value can be wrong, its
bounds (``metadata``: ``gt``/``ge``/``lt``/``le``, ``choices``, ``min_len``; on a list they apply to each
item). ``env``, ``algo`` and ``encoder`` have one schema per option, chosen by their ``name`` key
(:data:`ENV_SCHEMAS`, :data:`ALGO_SCHEMAS`, :data:`ENCODER_SCHEMAS`). The schemas are registered in
Hydra's ConfigStore (group ``schema``: ``schema/env/replay``, ``schema/algo/td3``, ...).

:mod:`crowdbench.config_check` validates configs against them (``validate``, ``validate_checkpoint``).

Nothing that an evaluation imports (crowdbench/leaderboard/cache.py ``EVAL_MODULES``) imports this module.
"""

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from crowdbench.baselines.params import OracleSettings, OrcaSettings
from crowdbench.config_fields import SEED_BOUNDS, bounded
from crowdbench.envs.crowdnav import CrowdNavConfig
from crowdbench.envs.humans.reactive_replay import ReactiveParams
from crowdbench.envs.rules import SimConfig
from crowdbench.envs.selfplay import SCENARIOS as SELFPLAY_SCENARIOS
from crowdbench.envs.selfplay import SelfPlayConfig

MAX_ENV_BATCH = 65536  # 256x the largest recipe's (experiment=ppo)


# ------------------------------------------------------------------------------------------------ env
# The env schemas are the runtime settings classes themselves (their fields carry the bounds:
# crowdbench/envs/rules.py SimConfig, envs/selfplay.py SelfPlayConfig, envs/crowdnav.py CrowdNavConfig,
# envs/humans/reactive_replay.py ReactiveParams), plus the keys that are not simulator settings: the env's
# name, its training batch and its evaluation set.


def _name(env: str):
    return bounded(env, choices=(env,))


def _batch():
    # parallel environments for training; bounded so that a typo (1e8) is an error, not GBs of tensors
    return bounded(16, ge=1, le=MAX_ENV_BATCH)


@dataclass
class ReplayEnvConfig(SimConfig):
    """``env=replay``: one robot among replayed ETH/UCY pedestrians (protocols v1 and v2)."""

    name: str = _name("replay")
    batch: int = _batch()
    scene: str = "students001"
    humans: str = bounded("replay", choices=("replay", "reactive_replay"))
    reactive: ReactiveParams = field(default_factory=ReactiveParams)


@dataclass
class SelfPlayEnvConfig(SelfPlayConfig):
    """``env=selfplay`` and its evaluation set."""

    name: str = _name("selfplay")
    batch: int = _batch()
    eval_scenarios: list[str] = field(default_factory=lambda: ["circle", "square"], metadata={"min_len": 1,
                                        "choices": SELFPLAY_SCENARIOS})
    eval_n_agents: list[int] | None = field(default=None, metadata={"min_len": 1, "ge": 1})
    eval_episodes: int = bounded(100, ge=1)
    eval_seed: int = bounded(20261122, **SEED_BOUNDS)


@dataclass
class CrowdNavEnvConfig(CrowdNavConfig):
    """``env=crowdnav`` and its test cases."""

    name: str = _name("crowdnav")
    batch: int = _batch()
    eval_settings: list[str] | None = field(default=None, metadata={"min_len": 1})  # e.g. [circle_n5]
    eval_episodes: int | None = bounded(None, ge=1)


ENV_SCHEMAS: dict[str, type] = {"replay": ReplayEnvConfig, "selfplay": SelfPlayEnvConfig, "crowdnav": CrowdNavEnvConfig}


# ---------------------------------------------------------------------------------------------- algo
class _AlgoSchemas(Mapping):
    """``algo`` schemas live with their algorithm (``crowdbench/algos/td3.py`` ``TD3Config``, ...): read
    from the registry (crowdbench/algos/registry.py) when first needed, so that importing this module
    imports no training code and an algorithm registered later is seen."""

    def __getitem__(self, name):
        from crowdbench.algos.registry import component, names

        if name not in names():
            raise KeyError(name)
        return component(name).config

    def __iter__(self):
        from crowdbench.algos.registry import names

        return iter(names())

    def __len__(self):
        from crowdbench.algos.registry import names

        return len(names())


ALGO_SCHEMAS: Mapping[str, type] = _AlgoSchemas()


# ------------------------------------------------------------------------------------------- encoder
@dataclass
class GCNConfig:
    """``encoder=gcn`` (crowdbench/models/gcn.py)."""

    name: str = bounded("gcn", choices=("gcn",))
    dim: int = bounded(32, ge=1)
    layers: int = bounded(2, ge=1)
    k: int = bounded(8, ge=1)  # neighbour cap per node
    radius2: float = bounded(5.0, gt=0)  # squared edge radius
    receptive_field: bool = True
    robot_radius2: float | None = bounded(None, gt=0)  # the robot's incoming edges (null: radius2)


@dataclass
class GatedGCNConfig(GCNConfig):
    """``encoder=gatedgcn`` (crowdbench/models/gatedgcn.py)."""

    name: str = bounded("gatedgcn", choices=("gatedgcn",))
    eps: float = bounded(1.0e-6, gt=0)  # gate normaliser
    edge_dist: bool = False  # each edge attribute carries |p_j - p_i| after p_j - p_i


@dataclass
class MLPConfig:
    """``encoder=mlp`` (crowdbench/models/mlp.py)."""

    name: str = bounded("mlp", choices=("mlp",))
    dim: int = bounded(32, ge=1)
    hidden: list[int] = field(default_factory=lambda: [256, 256], metadata={"ge": 1})
    max_humans: int = bounded(40, ge=0)


@dataclass
class SARLConfig:
    """``encoder=sarl`` (crowdbench/models/sarl.py)."""

    name: str = bounded("sarl", choices=("sarl",))
    dim: int = bounded(32, ge=1)
    embed: list[int] = field(default_factory=lambda: [64, 32], metadata={"ge": 1, "min_len": 1})
    interact: list[int] = field(default_factory=lambda: [32, 32], metadata={"ge": 1, "min_len": 1})
    attention: list[int] = field(default_factory=lambda: [32], metadata={"ge": 1})
    hidden: list[int] = field(default_factory=lambda: [64], metadata={"ge": 1})
    score_cap: float | None = bounded(None, gt=0)  # attention logits squashed into (-cap, cap) (models/base.py soft_cap)
    compact: bool = False  # compacted human slots in training updates (models/compact.py)


@dataclass
class LSTMRLConfig:
    """``encoder=lstm_rl`` (crowdbench/models/lstm_rl.py)."""

    name: str = bounded("lstm_rl", choices=("lstm_rl",))
    dim: int = bounded(32, ge=1)
    hidden_size: int = bounded(32, ge=1)  # LSTM state
    hidden: list[int] = field(default_factory=lambda: [64], metadata={"ge": 1})


@dataclass
class RGLConfig:
    """``encoder=rgl`` (crowdbench/models/rgl.py)."""

    name: str = bounded("rgl", choices=("rgl",))
    dim: int = bounded(32, ge=1)
    embed: list[int] = field(default_factory=lambda: [64], metadata={"ge": 1})
    layers: int = bounded(2, ge=1)
    skip: bool = True
    similarity: str = bounded("cosine", choices=("cosine", "embedded_gaussian"))  # adjacency logits
    scale: float = bounded(5.0, gt=0)  # cosine logits lie in [-scale, scale]
    compact: bool = True  # compacted human slots in training updates (models/compact.py)


@dataclass
class GATConfig(GCNConfig):
    """``encoder=gat`` (crowdbench/models/gat.py)."""

    name: str = bounded("gat", choices=("gat",))
    heads: int = bounded(4, ge=1)  # hidden-layer heads (concatenated; encoder.dim must be a multiple)
    out_heads: int = bounded(1, ge=1)  # last-layer heads (averaged)
    negative_slope: float = bounded(0.2, ge=0)  # LeakyReLU of the attention scores
    edge_features: bool = True  # relative positions in the scores
    score_cap: float | None = bounded(None, gt=0)  # attention logits squashed into (-cap, cap) (models/base.py soft_cap)


@dataclass
class DSRNNConfig:
    """``encoder=dsrnn`` (crowdbench/models/dsrnn.py)."""

    name: str = bounded("dsrnn", choices=("dsrnn",))
    dim: int = bounded(32, ge=1)
    embed: int = bounded(32, ge=1)  # edge / node embedding width
    attn_dim: int = bounded(32, ge=1)  # query / key width
    spatial_velocity: bool = True  # relative velocity in the spatial edges (DS-RNN: positions only)
    score_cap: float | None = bounded(None, gt=0)  # attention logits squashed into (-cap, cap) (models/base.py soft_cap)
    compact: bool = False  # compacted human slots in training updates (models/compact.py)



ENCODER_SCHEMAS: dict[str, type] = {"gatedgcn": GatedGCNConfig, "gcn": GCNConfig, "mlp": MLPConfig,
                                    "sarl": SARLConfig, "lstm_rl": LSTMRLConfig, "rgl": RGLConfig,
                                    "gat": GATConfig, "dsrnn": DSRNNConfig}


# ------------------------------------------------------------------------------ the other groups, root
@dataclass
class EvalConfig:
    """``eval`` (the protocol's scenes are checked by name in crowdbench/app.py ``eval_options``)."""

    scenes: list[str] = field(default_factory=lambda: ["students003", "zara2", "hotel", "eth"],
                              metadata={"min_len": 1})
    episodes: int | None = bounded(None, ge=1)
    save_episodes: bool = False
    overwrite: bool = False  # replace the results.json already in out=


@dataclass
class TrainConfig:
    total_frames: int = bounded(143360, ge=1)
    frames_per_batch: int = bounded(256, ge=1)
    utd: float = bounded(0.5, ge=0)  # gradient updates per collected frame
    checkpoint_every: int = bounded(5000, ge=1)  # frames
    save_buffer: bool = True  # the replay buffer with each checkpoint
    stats_window: int = bounded(200, ge=1)  # episodes
    max_minutes: float | None = bounded(None, gt=0)
    budget_warm_start: bool = False  # max_minutes counts the warm start too
    probe_every: int = bounded(28672, ge=1)  # frames
    probe_scene: str = "students003"
    probe_episodes: int = bounded(50, ge=1)
    logger: str = bounded("csv", choices=("csv", "tensorboard", "wandb"))  # crowdbench/algos/loggers.py
    progress_reward: float = 0.1
    human_dropout: float = bounded(0.0, ge=0, le=1)  # a probability
    human_thinning: float = bounded(0.0, ge=0, le=1)  # a probability (env=replay's recorded humans)
    # the training scene replayed at each of these speeds (1 = as recorded; env=replay; data/scenes.py playback_scene)
    playback_speeds: list[float] = field(default_factory=lambda: [1.0], metadata={"min_len": 1, "gt": 0, "le": 4})
    # self-play, on-policy: curriculum_agents[i] agents until curriculum_frames[i] frames, then env.n_agents
    # (crowdbench/algos/curriculum.py; the cross-field rules are checked there, before training)
    curriculum_agents: list[int] = field(default_factory=list, metadata={"ge": 1})
    curriculum_frames: list[int] = field(default_factory=list, metadata={"ge": 1})
    # imitation warm start before RL (crowdbench/algos/pretrain.py); a resumed run never repeats it
    pretrain: str | None = bounded(None, choices=("orca", "checkpoint"))
    pretrain_checkpoint: str | None = None  # pretrain=checkpoint: the expert (a value entry: lookahead cv)
    pretrain_frames: int = bounded(20000, ge=1)  # env steps of demonstrations
    pretrain_epochs: int = bounded(3, ge=0)  # passes over the demonstrations, actor and each critic
    pretrain_batch: int = bounded(256, ge=1)
    pretrain_lr: float = bounded(1.0e-3, gt=0)
    pretrain_heldout: float = bounded(0.1, ge=0, lt=1)  # share of demonstrated episodes kept for measuring
    # off-policy: weight of a behaviour-cloning term on demonstrations in the actor loss (0 = none), decaying
    # linearly to 0 over pretrain_bc_updates gradient updates (0 = constant)
    pretrain_bc_weight: float = bounded(0.0, ge=0)
    pretrain_bc_updates: int = bounded(20000, ge=0)
    # DAgger (crowdbench/algos/pretrain.py dagger): rounds of the student acting and the expert labelling
    pretrain_dagger_rounds: int = bounded(0, ge=0)
    pretrain_dagger_frames: int = bounded(5000, ge=1)  # env steps per round


@dataclass
class VizConfig:
    record: bool = False
    episodes: list[int] = field(default_factory=lambda: [0], metadata={"ge": 0})  # protocol episode ids
    scenes: list[str] | None = None
    dir: str = "recordings"
    trail_s: float = bounded(2.0, ge=0)


OrcaConfig = OrcaSettings  # the robot's ORCA baseline: crowdbench/baselines/params.py


OracleConfig = OracleSettings  # the oracle's search: crowdbench/baselines/params.py


@dataclass
class SubmissionConfig:
    experiment: str | None = None
    method: str = "${encoder.name}_${algo.name}"
    tag: str = ""
    suffix: str = ""
    name: str = "${submission.method}_${submission.tag}s${seed}"
    entry: str | None = None


@dataclass
class RootConfig:
    """``conf/config.yaml``; ``env``, ``algo``, ``encoder``: the schema their ``name`` selects."""

    env: Any = None
    eval: EvalConfig = field(default_factory=EvalConfig)
    algo: Any = None
    encoder: Any = None
    train: TrainConfig = field(default_factory=TrainConfig)
    viz: VizConfig = field(default_factory=VizConfig)
    seed: int = bounded(0, **SEED_BOUNDS)
    cpus: int = bounded(1, ge=1)
    policy: str = "orca"  # orca | straight | oracle | a checkpoint path (crowdbench/policies.py)
    out: str | None = ""
    resume: bool = False
    orca: OrcaConfig = field(default_factory=OrcaConfig)
    oracle: OracleConfig = field(default_factory=OracleConfig)
    submission: SubmissionConfig = field(default_factory=SubmissionConfig)


SELECTED = {"env": (ENV_SCHEMAS, "replay"), "algo": (ALGO_SCHEMAS, "td3"), "encoder": (ENCODER_SCHEMAS, "gatedgcn")}


def register() -> None:
    """Store the schemas in Hydra's ConfigStore: ``schema`` (the root) and ``schema/<group>/<name>``."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    cs.store(group="schema", name="root", node=RootConfig)
    for group, (schemas, _) in SELECTED.items():
        for name, node in schemas.items():
            cs.store(group=f"schema/{group}", name=name, node=node)
    for group, node in (("eval", EvalConfig), ("train", TrainConfig), ("viz", VizConfig), ("orca", OrcaConfig),
                        ("oracle", OracleConfig), ("submission", SubmissionConfig)):
        cs.store(group=f"schema/{group}", name="default", node=node)


register()
