"""The one place that turns the ``env`` config into a world, a scenario and the envs over them.

``env.name`` picks the world from :data:`WORLDS`: ``replay`` (one robot among replayed ETH/UCY
pedestrians, protocols v1 and v2), ``selfplay`` (``n_agents`` learning agents, optional replayed
background) or ``crowdnav`` (one robot among ORCA or social-force humans, CrowdNav's circle and square
crossing). Which protocol evaluates a world is the protocols' business (crowdbench/protocols/).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from crowdbench.data.scenes import Scene
from crowdbench.envs.humans.replay import NoCrowd, ReplayCrowd
from crowdbench.envs.rules import SimConfig
from crowdbench.envs.world import World

REPLAY_HUMANS = ("replay", "reactive_replay")


@dataclass(frozen=True)
class WorldKind:
    """How ``env.name`` builds its world: ``config()`` is its simulator config class (a
    :class:`SimConfig`), ``build(env_cfg, cfg, batch)`` returns ``(world, scenario)``."""

    config: Callable[[], type]
    build: Callable
    # ``playback(env_cfg, cfg, batch, speeds)``: the world with its recorded training scene replayed at each of
    # ``speeds`` (``train.playback_speeds``); None for a world that replays no recording
    playback: Callable | None = None


WORLDS: dict[str, WorldKind] = {}


def register_world(name: str, config: Callable[[], type], build: Callable, playback: Callable | None = None) -> None:
    """Make ``env.name=NAME`` build worlds with ``build``, typed by the class ``config()`` returns."""
    WORLDS[name] = WorldKind(config, build, playback)


def env_name(env_cfg) -> str:
    name = str(env_cfg.get("name", "replay"))
    if name not in WORLDS:
        raise ValueError(f"unknown env.name {name!r}; valid: {', '.join(WORLDS)}")
    return name


def selfplay_config(env_cfg, **overrides):
    from crowdbench.envs.selfplay import SelfPlayConfig

    return SelfPlayConfig(**{**SelfPlayConfig.fields_of(env_cfg), **overrides})


def replay_world(scene: str | Scene, batch: int, cfg: SimConfig | None = None, reactive=None, sfm=None):
    """``(world, scenario)`` on ``scene``: one robot among the recorded humans, replayed as recorded
    (protocol v1) or, with ``reactive`` (a :class:`~crowdbench.envs.humans.reactive_replay.ReactiveParams`),
    yielding to the robot (protocol v2; ``sfm``: the social-force parameters)."""
    from crowdbench.envs.scenarios import ReplayScenario, replay_scene

    cfg = cfg or SimConfig()
    scene = replay_scene(scene, cfg) if isinstance(scene, str) else scene
    if reactive is None:
        crowd = ReplayCrowd(scene, batch, cfg.time_limit)
    else:
        from crowdbench.envs.humans.reactive_replay import ReactiveReplayCrowd

        crowd = ReactiveReplayCrowd(scene, batch, cfg.time_limit, cfg.dt, cfg.human_radius, cfg.robot_radius, reactive, sfm)
    return World(batch, cfg, crowd), ReplayScenario(scene, cfg)


def replay_humans(env_cfg):
    """The ``env.humans`` of the replay protocol: None (``replay``, as recorded) or the
    :class:`~crowdbench.envs.humans.reactive_replay.ReactiveParams` of ``reactive_replay``."""
    humans = str(env_cfg.get("humans", "replay"))
    if humans not in REPLAY_HUMANS:
        raise ValueError(f"unknown env.humans {humans!r} for env.name=replay; valid: {', '.join(REPLAY_HUMANS)}")
    if humans == "replay":
        return None
    from crowdbench.envs.humans.reactive_replay import ReactiveParams

    return ReactiveParams.of(env_cfg.get("reactive"))


def selfplay_world(cfg, batch: int):
    """``(world, scenario)`` of self-play with ``cfg`` (a :class:`SelfPlayConfig`)."""
    from crowdbench.envs.selfplay import SelfPlayScenario, background_scene

    scene = background_scene(cfg)
    if cfg.n_humans:
        from crowdbench.envs.humans.reactive import reactive_crowd

        crowd = reactive_crowd(cfg, batch)
    else:
        crowd = ReplayCrowd(scene, batch, cfg.time_limit) if scene is not None else NoCrowd(batch)
    world = World(batch, cfg, crowd, n_agents=cfg.n_agents, interact=True, done_agents=cfg.done_agents)
    return world, SelfPlayScenario(cfg, scene)


def crowdnav_world(cfg, batch: int):
    """``(world, scenario)`` of the CrowdNav protocol with ``cfg`` (a :class:`CrowdNavConfig`)."""
    from crowdbench.envs.crowdnav import CrowdNavScenario, crowdnav_crowd

    return World(batch, cfg, crowdnav_crowd(cfg, batch)), CrowdNavScenario(cfg)


def sim_config(env_cfg, **overrides):
    """The typed simulator config of ``env_cfg`` (:class:`SimConfig` or its per-world subclass)."""
    cls = WORLDS[env_name(env_cfg)].config()
    return cls(**{**cls.fields_of(env_cfg), **overrides})


def make_world(env_cfg, batch: int, **overrides):
    """``(world, scenario)`` for the ``env`` config (``overrides``: simulator settings, e.g. ``frame``)."""
    return WORLDS[env_name(env_cfg)].build(env_cfg, sim_config(env_cfg, **overrides), batch)


def _selfplay_config_class():
    from crowdbench.envs.selfplay import SelfPlayConfig

    return SelfPlayConfig


def _crowdnav_config_class():
    from crowdbench.envs.crowdnav import CrowdNavConfig

    return CrowdNavConfig


def replay_playback(env_cfg, cfg, batch: int, speeds):
    from crowdbench.envs.scenarios import replay_scene_at

    return replay_world(replay_scene_at(str(env_cfg.scene), cfg, speeds), batch, cfg, replay_humans(env_cfg))


register_world("replay", lambda: SimConfig,
               lambda env_cfg, cfg, batch: replay_world(str(env_cfg.scene), batch, cfg, replay_humans(env_cfg)),
               replay_playback)
register_world("selfplay", _selfplay_config_class, lambda env_cfg, cfg, batch: selfplay_world(cfg, batch))
register_world("crowdnav", _crowdnav_config_class, lambda env_cfg, cfg, batch: crowdnav_world(cfg, batch))


def training_world(env_cfg, batch: int, playback_speeds=(1.0,)):
    """``(world, scenario)`` of :func:`make_world`, the replayed scene played at each of ``playback_speeds``
    (``train.playback_speeds``, training only: :func:`~crowdbench.envs.scenarios.replay_scene_at`)."""
    speeds = tuple(float(f) for f in playback_speeds)
    if speeds == (1.0,):
        return make_world(env_cfg, batch)
    name = env_name(env_cfg)
    if WORLDS[name].playback is None:
        raise ValueError(f"train.playback_speeds: env.name={name} replays no recording (env.name=replay does)")
    return WORLDS[name].playback(env_cfg, sim_config(env_cfg), batch, speeds)


def make_env(cfg, progress_reward: float = 0.0, human_dropout: float = 0.0, extra=(), playback_speeds=(1.0,),
             human_thinning: float = 0.0):
    """The TorchRL env of ``cfg.env``, ``env.batch`` wide, seeded with ``cfg.seed``.

    ``progress_reward`` (``train.progress_reward``), ``human_dropout`` (``train.human_dropout``) and
    ``human_thinning`` (``train.human_thinning``) are training-only transforms (:mod:`crowdbench.envs.transforms`);
    ``extra`` transforms go after them.
    ``playback_speeds`` (``train.playback_speeds``): :func:`training_world`.
    """
    from torchrl.envs import Compose, TransformedEnv

    from crowdbench.envs.torchrl_env import CrowdEnv
    from crowdbench.envs.transforms import HumanDropout, HumanThinning, ProgressReward

    world, scenario = training_world(cfg.env, int(cfg.env.batch), playback_speeds)
    env = CrowdEnv(world, scenario, seed=cfg.seed)
    transforms = []
    if human_thinning:
        transforms.append(HumanThinning(human_thinning, cfg.seed))
    if human_dropout:
        transforms.append(HumanDropout(human_dropout, cfg.seed, world.M, world.Mh))
    if progress_reward:
        transforms.append(ProgressReward(progress_reward))
    transforms += list(extra)
    return TransformedEnv(env, Compose(*transforms)) if transforms else env


def make_parallel_env(env_cfg, **overrides):
    """The PettingZoo ``ParallelEnv`` (one environment) of ``env_cfg``."""
    from crowdbench.envs.pettingzoo_env import CrowdParallelEnv

    return CrowdParallelEnv(*make_world(env_cfg, 1, **overrides))


def replay_env(scene: str = "students001", batch: int = 1, cfg: SimConfig | None = None, seed: int = 0,
               episodes=None, reactive=None):
    """The TorchRL env of protocol v1 on ``scene`` (``episodes``: an optional fixed list ``(t0 [E], angle [E])``;
    ``reactive``: :class:`~crowdbench.envs.humans.reactive_replay.ReactiveParams` for protocol v2's humans)."""
    from crowdbench.envs.torchrl_env import CrowdEnv

    world, scenario = replay_world(scene, batch, cfg, reactive)
    if episodes is not None and not isinstance(episodes, dict):
        episodes = scenario.episodes(*episodes)
    return CrowdEnv(world, scenario, seed=seed, episodes=episodes)


def replay_parallel_env(scene: str = "students001", cfg: SimConfig | None = None, render_mode: str | None = None):
    """The PettingZoo env of protocol v1 on ``scene`` (one robot, the training distribution of episodes)."""
    from crowdbench.envs.pettingzoo_env import CrowdParallelEnv

    return CrowdParallelEnv(*replay_world(scene, 1, cfg), render_mode=render_mode)


def selfplay_env(batch: int = 1, cfg=None, seed: int = 0, episodes: dict | None = None):
    """The TorchRL self-play env of ``cfg`` (a :class:`SelfPlayConfig`; default: 8 agents, circle)."""
    from crowdbench.envs.selfplay import SelfPlayConfig
    from crowdbench.envs.torchrl_env import CrowdEnv

    world, scenario = selfplay_world(cfg or SelfPlayConfig(), batch)
    return CrowdEnv(world, scenario, seed=seed, episodes=episodes)


def selfplay_parallel_env(cfg=None, render_mode: str | None = None):
    """The PettingZoo self-play env of ``cfg`` (agents ``agent_0 ..``)."""
    from crowdbench.envs.pettingzoo_env import CrowdParallelEnv
    from crowdbench.envs.selfplay import SelfPlayConfig

    return CrowdParallelEnv(*selfplay_world(cfg or SelfPlayConfig(), 1), render_mode=render_mode)
