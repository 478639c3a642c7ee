"""The CrowdNav protocol: CrowdNav's 500 test cases -> batched rollout through the env -> metrics -> results JSON.

Setting ``circle_n5`` is circle crossing with 5 humans (``square_n20``: square crossing, 20 humans);
episode ``i`` is CrowdNav's test case ``i`` (:mod:`crowdbench.envs.crowdnav_cases`). The metrics are
protocol v1's (:func:`crowdbench.protocols.engine.episode_metrics`), with CrowdNav's discomfort distance as the
danger distance. The oracle is privileged only with an invisible robot: the humans' future then
does not depend on the robot, so it is simulated once without it and handed to the planner.
"""

from __future__ import annotations

import re
from dataclasses import asdict, replace
from pathlib import Path
from types import SimpleNamespace

import torch

from crowdbench.data.scenes import Scene
from crowdbench.envs.crowdnav import CrowdNavConfig, CrowdNavScenario, crowdnav_crowd, list_digest
from crowdbench.envs.factory import crowdnav_world, env_name
from crowdbench.envs.observation import Policy
from crowdbench.envs.torchrl_env import CrowdEnv
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

PROTOCOL = "crowdnav-v1"
SETTING = re.compile(r"^(circle|square)_n([1-9][0-9]*)$")


def parse_setting(name: str) -> tuple[str, int]:
    m = SETTING.match(str(name))
    if not m:
        raise ValueError(f"unknown CrowdNav setting {name!r}; valid: circle_n<humans> or square_n<humans>, e.g. circle_n5")
    return m.group(1), int(m.group(2))


def crowdnav_digests(cfg, settings) -> dict[str, str]:
    """The digests of ``settings``' CrowdNav test lists under ``cfg`` (generated once per process:
    the evaluation that follows reuses them)."""
    out = {}
    for s in settings:
        scenario, n = parse_setting(s)
        out[s] = list_digest(CrowdNavScenario(replace(cfg, scenario=scenario, n_humans=n)).test_list())
    return out


def future_view(world, cfg: CrowdNavConfig, episodes: dict[str, torch.Tensor]):
    """What the oracle plans against: the humans' whole future, simulated without the robot, laid out as
    one :class:`Scene` whose episode ``b`` starts at grid index ``b * (T + 1)``."""
    B, T, M = world.B, cfg.time_limit, cfg.n_humans
    crowd = crowdnav_crowd(replace(cfg, robot_visible=False), B)
    crowd.reset(torch.ones(B, dtype=torch.bool), torch.arange(B), episodes)
    pos, vel = [crowd.pos.clone()], [crowd.vel.clone()]
    running = torch.ones(B, dtype=torch.bool)
    for _ in range(T):
        crowd.advance(running, None)
        pos.append(crowd.pos.clone())
        vel.append(crowd.vel.clone())
    P, V = torch.stack(pos, 1), torch.stack(vel, 1)  # [B, T + 1, M, 2]
    prev = torch.cat((P[:, :1], P[:, :-1]), 1)
    flat = lambda x: x.reshape(B * (T + 1), *x.shape[2:])
    scene = Scene(name="crowdnav-future", dt=cfg.dt, row_period=cfg.dt, pos=flat(P), prev=flat(prev), vel=flat(V),
                  valid=torch.ones(B * (T + 1), M, dtype=torch.bool), ped_id=flat(torch.arange(M).expand(B, T + 1, M)),
                  centre=torch.zeros(2))
    return SimpleNamespace(B=B, t=torch.arange(B) * (T + 1), scene=scene, pos=world.pos, goal=world.goal, cfg=world.cfg,
                           radius_sum=world.radius_sum, M=M, clip_action=world.clip_action)


def evaluate_crowdnav(policy: Policy, cfg: CrowdNavConfig, settings=None, episodes: int | None = None,
                      out_dir: Path | None = None, save_episodes: bool = False, meta: dict | None = None,
                      phase: str = "test") -> dict:
    """Evaluate ``policy`` on CrowdNav's test cases of every setting (default: ``cfg``'s scenario and crowd size);
    ``phase="val"``: its 100 validation cases instead (the training probe)."""
    settings = [f"{cfg.scenario}_n{cfg.n_humans}"] if not settings else [str(s) for s in settings]
    parsed = [parse_setting(s) for s in settings]
    privileged = getattr(policy, "privileged", False)
    if privileged and cfg.robot_visible:
        raise ValueError("the oracle knows the humans' future, which depends on a visible robot: "
                         "available with env.robot_visible=false only")
    results = {"protocol": PROTOCOL if phase == "test" else f"{PROTOCOL}-{phase}", "policy": policy.name, "meta": meta or {}, "numerics": describe(),
               "humans": cfg.humans, "robot_visible": cfg.robot_visible, "scenes": {}, "lists": {}}
    results.update(privilege_labels(policy))
    rows = []
    for name, (scenario, n) in zip(settings, parsed, strict=True):
        c = replace(cfg, scenario=scenario, n_humans=n, frame=policy.frame)
        full = CrowdNavScenario(c).test_list(phase)
        results["lists"][name] = list_digest(full)
        keep = torch.tensor([e["episode"] for e in select_episodes({"episodes": [{"episode": i} for i in
                                                                                 range(len(full["case"]))]}, episodes)])
        eps = {k: v[keep] for k, v in full.items()}
        world, scen = crowdnav_world(c, len(keep))
        env = CrowdEnv(world, scen, episodes=eps)
        view = future_view(world, c, eps) if privileged else None
        tr = robot_traces(env, policy, privileged_view=view)
        m = episode_metrics(tr, c)
        results["scenes"][name] = aggregate(m, PROTOCOL)
        if save_episodes:
            rows += episode_rows(name, eps, tr, m, c)
    # orca_backend is how, not what: both solvers give the same numbers (results stay comparable); the
    # numba social force is not bit-identical to torch's, so sfm_backend is written when it is not torch
    skip = ("scenario", "n_humans", "frame", "orca_backend") + (("sfm_backend",) if cfg.sfm_backend == "torch" else ())
    results["sim_config"] = {k: v for k, v in asdict(cfg).items() if k not in skip}
    if out_dir is not None:
        write_results(out_dir, results, rows if save_episodes else None)
    return results


def episode_rows(setting: str, eps: dict, tr: dict, m: dict, cfg: CrowdNavConfig) -> list[dict]:
    from crowdbench.envs.rules import OUTCOMES

    rows = []
    for b, case in enumerate(eps["case"].tolist()):
        n = int(m["steps"][b])
        ok = bool(m["success"][b])
        rows.append({"protocol": PROTOCOL, "setting": setting, "episode": case, "dt": cfg.dt,
                     "robot_xy": [[round(x, 5) for x in p] for p in tr["xy"][: n + 1, b].tolist()],
                     "outcome": OUTCOMES[int(m["outcome"][b])], "nav_time_s": float(m["nav_time"][b]) if ok else None,
                     "danger_steps": int(m["danger_steps"][b]), "min_clearance": float(m["min_clearance"][b])})
    return rows


def _track(setting: str, humans: int, kind: str) -> Track:
    return Track(f"crowdnav-{setting.replace('_n', '')}", f"CrowdNav {kind} crossing, {humans} ORCA humans, invisible robot",
                 "crowdnav", setting=setting)


class CrowdNavProtocol(Protocol):
    """CrowdNav's test cases of each ``env.eval_settings``; its validation cases are the training probe."""

    name, label, world, command = "crowdnav", PROTOCOL, "crowdnav", "eval-crowdnav"
    tracks = (_track("circle_n5", 5, "circle"), _track("circle_n20", 20, "circle"), _track("square_n5", 5, "square"))

    def selects(self, env_cfg) -> bool:
        return env_name(env_cfg) == self.world

    def run(self, policy, cfg, out: Path, overrides: list[str], strict: bool = True, progress=None) -> dict:
        from crowdbench.protocols.lists import check_crowdnav

        e = cfg.env
        c = self.sim_config(e)
        check_crowdnav(crowdnav_digests(c, list(e.eval_settings or [f"{c.scenario}_n{c.n_humans}"])))
        return evaluate_crowdnav(policy, c, None if e.eval_settings is None else list(e.eval_settings),
                                 e.eval_episodes, out_dir=out, save_episodes=bool(cfg.eval.save_episodes),
                                 meta={"seed": cfg.seed, "overrides": overrides})

    def probe(self, cfg):
        from crowdbench.algos.checkpoint import LearnedPolicy

        sim = self.sim_config(cfg.env)
        setting = f"{sim.scenario}_n{sim.n_humans}"

        def probe_crowdnav(actor) -> dict[str, float]:  # the validation cases: CrowdNav's own held-out set
            res = evaluate_crowdnav(LearnedPolicy(actor, frame=cfg.env.frame), sim, [setting],
                                    cfg.train.probe_episodes, phase="val")["scenes"][setting]
            return {f"probe_crowdnav_{setting}_success": res["success_rate"]["mean"],
                    f"probe_crowdnav_{setting}_collision": res["collision_rate"]["mean"]}

        return probe_crowdnav

    def evaluate_track(self, track: Track, policy, scenes: list[str], episodes: int | None, out_dir, meta: dict,
                       env=None, save_episodes: bool = True) -> dict:
        cfg = replace(self.sim_config(env), frame=policy.frame)
        return evaluate_crowdnav(policy, cfg, [track.setting], episodes, out_dir=out_dir,
                                 save_episodes=save_episodes, meta=meta)

    short = "CrowdNav"

    def where(self, track: Track) -> str:
        return f"CrowdNav's test cases of {track.setting}"

    def track_overrides(self, track: Track) -> tuple[str, ...]:
        scenario, n = parse_setting(track.setting)
        return ("env=crowdnav", f"env.scenario={scenario}", f"env.n_humans={n}")

    def check_results(self, results: dict) -> None:
        from crowdbench.protocols.lists import check_crowdnav

        check_crowdnav(results.get("lists", {}))

    def trained_track(self, env: dict) -> str | None:
        if env.get("humans", "orca") != "orca" or env.get("robot_visible", False):
            return None
        track = f"crowdnav-{env.get('scenario', 'circle')}{env.get('n_humans', 5)}"
        return track if track in {t.name for t in self.tracks} else None
