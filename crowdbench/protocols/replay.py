"""Protocol v1 (docs/protocol.md): one robot among the recorded ETH/UCY pedestrians, who never yield.

Saved episode list of each evaluation scene -> batched rollout -> metrics with 95% CIs -> results JSON.
:class:`ReplayProtocol` is also protocol v2's base (crowdbench/protocols/reactive_replay.py): the same
episodes, the same loop, reactive humans.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from pathlib import Path

from crowdbench.data.scenes import check_scene
from crowdbench.envs.factory import env_name, replay_humans, replay_world
from crowdbench.envs.observation import Policy
from crowdbench.envs.protocol import (
    EVAL_SCENES,
    PAPER_SCENES,
    PROTOCOL_DIR,
    PROTOCOL_VERSION,
    V2,
    V2_MODELS,
    ProtocolSpec,
    load_episodes,
    load_episodes_v2,
    reactive_params,
    v2_humans,
)
from crowdbench.envs.rules import OUTCOMES, SimConfig
from crowdbench.envs.torchrl_env import CrowdEnv
from crowdbench.metric_table import IN_AVERAGE, in_table
from crowdbench.numerics import describe
from crowdbench.protocols.base import Protocol, Track
from crowdbench.protocols.engine import (
    aggregate,
    episode_metrics,
    privilege_labels,
    robot_traces,
    select_episodes,
    write_results,
)


def rollout(policy: Policy, scene, episodes: list[dict], cfg: SimConfig, recorder=None, reactive=None) -> dict:
    """Run ``episodes`` of ``scene`` (a name or a :class:`~crowdbench.data.scenes.Scene`) in one batch
    through the env (``reactive``: protocol v2's ``(ReactiveParams, SFMParams)``); return per-step traces ``[T, B]``."""
    world, scenario = replay_world(scene, len(episodes), replace(cfg, frame=policy.frame), *(reactive or ()))
    return robot_traces(CrowdEnv(world, scenario, episodes=scenario.from_list(episodes)), policy, recorder)




def episode_records(scene: str, episodes: list[dict], tr: dict, m: dict, cfg: SimConfig,
                    protocol: str = PROTOCOL_VERSION) -> list[dict]:
    """Rows of ``episodes.jsonl`` in SPEC section 6's format."""
    rows = []
    for b, e in enumerate(episodes):
        n = int(m["steps"][b])
        ok = bool(m["success"][b])
        rows.append({
            "protocol": protocol, "scene": scene, "episode": e["episode"],
            "start_time_s": e["start_time_s"], "dt": cfg.dt, "start": e["start"], "goal": e["goal"],
            "robot_xy": [[round(x, 5) for x in p] for p in tr["xy"][: n + 1, b].tolist()],
            "outcome": OUTCOMES[int(m["outcome"][b])],
            "nav_time_s": float(m["nav_time"][b]) if ok else None,
            "danger_steps": int(m["danger_steps"][b]),
            "min_clearance": float(m["min_clearance"][b]),
        })
    return rows


def sim_config_for(spec: ProtocolSpec, **overrides) -> SimConfig:
    """The simulator configuration the protocol fixes (dt, time limit, time base, radius)."""
    return SimConfig(**{**overrides, "dt": spec.dt, "time_limit": spec.time_limit, "time_base": spec.time_base,
                        "start_radius": spec.start_radius})


def evaluate(policy: Policy, scenes=PAPER_SCENES, episodes: int | None = None, out_dir: Path | None = None,
             save_episodes: bool = False, sim_overrides: dict | None = None, meta: dict | None = None,
             recorder_factory=None, humans: str | None = None) -> dict:
    """Evaluate ``policy`` on the saved protocol episode lists; optionally write results files.

    ``humans``: None for protocol v1 (the recording), ``orca`` / ``sfm`` for protocol v2 (reactive replay
    with that model, its parameters fixed by the v2 lists)."""
    scenes = [check_scene(s) for s in scenes]
    if humans is not None and humans not in V2_MODELS:
        raise ValueError(f"unknown reactive model {humans!r}; valid: {', '.join(V2_MODELS)}")
    if humans is not None and getattr(policy, "privileged", False):
        raise ValueError("the oracle knows the humans' future, which in protocol v2 depends on the robot: "
                         "it has no privileged plan there (protocol v1 and CrowdNav with an invisible robot only)")
    protocol = PROTOCOL_VERSION if humans is None else V2
    results = {"protocol": protocol, "policy": policy.name, "meta": meta or {}, "numerics": describe(),
               "scenes": {}}
    if humans is not None:
        results["humans"] = humans
    results.update(privilege_labels(policy))
    rows = []
    for scene in scenes:
        saved = load_episodes(scene) if humans is None else load_episodes_v2(scene)
        spec = ProtocolSpec(**{**saved["spec"], "version": PROTOCOL_VERSION})
        cfg = sim_config_for(spec, **(sim_overrides or {}))
        eps = select_episodes(saved, episodes)
        recorder = recorder_factory(scene) if recorder_factory else None
        reactive = None if humans is None else reactive_params(saved, humans)
        tr = rollout(policy, scene, eps, cfg, recorder, reactive)
        m = episode_metrics(tr, cfg)
        results["scenes"][scene] = aggregate(m, protocol)
        if save_episodes:
            rows += episode_records(scene, eps, tr, m, cfg, protocol)
        results["sim_config"] = asdict(cfg)
        if reactive is not None:
            results["reactive"] = {**reactive[0].to_dict(), **({"social_force": asdict(reactive[1])}
                                                               if humans == "sfm" else {})}
    paper = [s for s in PAPER_SCENES if s in results["scenes"]]
    if paper:
        means = {x.key: [results["scenes"][s][x.key]["mean"] for s in paper] for x in in_table(IN_AVERAGE)}
        # an undefined scene value (no successful episode: no nav time) leaves the average undefined
        results["average_paper_scenes"] = {k: None if None in v else sum(v) / len(v) for k, v in means.items()}
    if out_dir is not None:
        write_results(out_dir, results, rows if save_episodes else None)
    return results




def scenes_of(cfg, allowed=EVAL_SCENES) -> tuple[list[str], int | None]:
    """``eval.scenes`` (each with a published list, among ``allowed``) and ``eval.episodes`` of ``cfg``."""
    from crowdbench.envs.rules import check_seed

    check_seed(cfg.seed)
    scenes = list(cfg.eval.scenes) if not isinstance(cfg.eval.scenes, str) else [cfg.eval.scenes]
    if not scenes:
        raise ValueError(f"eval.scenes is empty; evaluation scenes: {', '.join(allowed)}")
    scenes = [check_scene(s) for s in scenes]
    unlisted = [s for s in scenes if s not in allowed]
    if unlisted:
        raise ValueError(f"eval.scenes: {', '.join(unlisted)} has no protocol episode list (the training scene); "
                         f"evaluation scenes: {', '.join(allowed)}")
    episodes = cfg.eval.episodes
    if episodes is not None and (not isinstance(episodes, int) or episodes < 1):
        raise ValueError(f"eval.episodes must be a positive integer or null, got {episodes!r}")
    return scenes, episodes


def reactive_model(cfg, strict: bool = True) -> str | None:
    """The reactive model protocol v2 evaluates with (``env.humans=reactive_replay``), or None for v1.

    Training may use any ``env.reactive`` values; evaluation uses the protocol's, so ``crowdbench eval``
    (``strict``) refuses different ones rather than silently replace them, while a training run's probe
    and final evaluation (not strict) use the protocol's values for its model."""
    try:
        params = replay_humans(cfg.env)
    except TypeError as e:
        raise ValueError(str(e)) from None
    if params is None or not strict:
        return None if params is None else params.model
    fixed = reactive_params({"humans": v2_humans()}, params.model)[0]
    for key, value in fixed.to_dict().items():
        if getattr(params, key) != value:
            raise ValueError(f"env.reactive.{key}={getattr(params, key)} conflicts with protocol v2 ({value}); "
                             "evaluation always uses the protocol's value")
    return params.model


def check_fixed(cfg) -> None:
    """The protocol fixes dt, time limit, time base and start radius; refuse an override of them."""
    spec, env = ProtocolSpec(), SimConfig.fields_of(cfg.env)
    for key in ("dt", "time_limit", "time_base", "start_radius"):
        if str(env[key]) != str(getattr(spec, key)):
            raise ValueError(f"env.{key}={env[key]} conflicts with protocol {spec.version} ({getattr(spec, key)}); "
                             "evaluation always uses the protocol's value")


def replay_probe(cfg, humans: str | None):
    """Held-out check during training: success on ``probe_episodes`` of ``probe_scene``'s protocol list."""
    from crowdbench.algos.checkpoint import LearnedPolicy

    scene = check_scene(cfg.train.probe_scene)

    def probe(actor) -> dict[str, float]:
        res = evaluate(LearnedPolicy(actor, frame=cfg.env.frame), [scene], cfg.train.probe_episodes,
                       sim_overrides=SimConfig.fields_of(cfg.env), humans=humans)["scenes"][scene]
        return {f"probe_{scene}_success": res["success_rate"]["mean"],
                f"probe_{scene}_collision": res["collision_rate"]["mean"]}

    return probe


class ReplayProtocol(Protocol):
    """Protocol v1: the recorded humans; the evaluation scenes' saved lists, checked against their hashes."""

    name, label, world = "replay", PROTOCOL_VERSION, "replay"
    per_scene = True
    version = "v1"  # the published lists (crowdbench/protocols/lists.py)
    scenes = EVAL_SCENES  # the scenes with a published list
    list_dir = PROTOCOL_DIR
    tracks = (Track("v1", "Replay (protocol v1): the recorded ETH/UCY pedestrians, who never yield", "replay"),)

    def selects(self, env_cfg) -> bool:
        return env_name(env_cfg) == self.world and replay_humans(env_cfg) is None

    def humans_of(self, cfg, strict: bool = True) -> str | None:
        return reactive_model(cfg, strict)

    def check(self, cfg, policy_name: str) -> None:
        scenes_of(cfg, self.scenes)
        check_fixed(cfg)
        self.humans_of(cfg)

    def run(self, policy, cfg, out: Path, overrides: list[str], strict: bool = True, progress=None) -> dict:
        import contextlib

        scenes, episodes = scenes_of(cfg, self.scenes)
        sim = SimConfig.fields_of(cfg.env)
        steps = SimConfig(**sim).time_limit  # bad env values (the frame too, replaced below) are one-line errors
        sim["frame"] = policy.frame
        humans = self.humans_of(cfg, strict)
        self.check_lists(scenes)  # the published lists, not look-alikes
        bar = progress(scenes, steps) if progress else contextlib.nullcontext()
        with bar as recorders:
            return evaluate(policy, scenes, episodes, out_dir=out, save_episodes=bool(cfg.eval.save_episodes),
                            sim_overrides=sim, meta={"seed": cfg.seed, "overrides": overrides},
                            recorder_factory=recorders, humans=humans)

    def probe(self, cfg):
        return replay_probe(cfg, self.humans_of(cfg, strict=False))

    def evaluate_track(self, track: Track, policy, scenes: list[str], episodes: int | None, out_dir, meta: dict,
                       env=None, save_episodes: bool = True) -> dict:
        return evaluate(policy, scenes, episodes, out_dir=out_dir, save_episodes=save_episodes,
                        sim_overrides={"frame": policy.frame}, meta=meta, humans=track.humans)

    def track_overrides(self, track: Track) -> tuple[str, ...]:
        return ("env.humans=reactive_replay", f"env.reactive.model={track.humans}") if track.humans else ()

    def list_files(self, track: Track, scenes: list[str]) -> list[Path]:
        return [self.list_dir / f"{s}.json" for s in scenes]

    def check_lists(self, scenes: list[str]) -> None:
        from crowdbench.protocols.lists import check_replay

        check_replay(self.version, scenes)

    def trained_track(self, env: dict) -> str | None:
        return "v1"
