"""The self-play protocol: a fixed seeded episode set -> batched rollout of all agents -> metrics -> results JSON.

Every agent of every episode acts from the same :class:`~crowdbench.envs.observation.Policy`
(a learned actor, ORCA or straight-to-goal), called once per step for the ``[E, A]`` agents
of the ``E`` episodes. Episodes come from :func:`crowdbench.envs.selfplay.episode_set` with
``eval_seed``: the same configuration gives the same starts and goals for every policy.

Metrics (docs/selfplay.md):

- per agent (``E * A`` agent-episodes; Wilson 95% intervals for rates, normal for means):
  success / collision / timeout rates, navigation time of arrived agents, dangers between
  agents (steps ending with ``0 <= d_agent < danger_dist``), dangers with any body, minimum
  agent-agent clearance at step ends over the episode, path length ratio of arrived agents;
- per episode: "all agents arrived" rate, rate of episodes with at least one collision,
  colliding agent pairs, agent-agent danger steps (summed over agents), episode time (until
  the last agent finished) of episodes where all arrived.
"""

from __future__ import annotations

import math
from dataclasses import asdict, replace
from pathlib import Path

import torch

from crowdbench.envs.factory import env_name, selfplay_config, selfplay_world
from crowdbench.envs.observation import Policy
from crowdbench.envs.rules import COLLISION, OUTCOMES, SUCCESS, TIMEOUT
from crowdbench.envs.selfplay import SelfPlayConfig, episode_set
from crowdbench.envs.torchrl_env import CrowdEnv
from crowdbench.metric_table import IN_SELFPLAY, in_table, metric
from crowdbench.protocols.base import Protocol, Track
from crowdbench.protocols.engine import drive, summarise, write_results
from crowdbench.protocols.selfplay_tracks import (
    EPISODES,
    SETTINGS,
    episodes_of,
    list_path,
    setting_overrides,
    track_name,
)

PROTOCOL = "selfplay-v1"
HOME = "selfplay"  # the training track of every self-play entry (submission.yaml's ``track``)
OUTCOME_CHAR = {SUCCESS: "S", COLLISION: "C", TIMEOUT: "T"}


def rollout(policy: Policy, cfg: SelfPlayConfig, episodes: dict) -> dict:
    """Run all ``episodes`` (``start``, ``goal`` ``[E, A, 2]``, ``t0`` ``[E]``) in one batch through the env;
    traces ``[T, E, A]``."""
    world, scenario = selfplay_world(replace(cfg, frame=policy.frame), len(episodes["start"]))
    env = CrowdEnv(world, scenario, episodes=episodes)
    xy, active, agent_clear, clear = [], [], [], []
    pairs = torch.zeros(world.B, world.A, world.A, dtype=torch.bool)

    def on_step(w, info):
        nonlocal pairs
        xy.append(w.pos.clone())
        active.append(info.active)
        agent_clear.append(info.extra["agent_clearance"])
        clear.append(info.clearance)
        pairs |= info.extra["pair_collision"]

    drive(env, policy, on_reset=lambda w: xy.append(w.pos.clone()), on_step=on_step)
    return {"xy": torch.stack(xy), "active": torch.stack(active), "agent_clearance": torch.stack(agent_clear),
            "clearance": torch.stack(clear), "outcome": world.outcome.clone(), "pairs": pairs,
            "start": world.start.clone(), "goal": world.goal.clone()}


def metrics(tr: dict, cfg: SelfPlayConfig) -> dict:
    act = tr["active"]  # [T, E, A]
    steps = act.sum(0).double()  # [E, A] steps each agent moved
    out = tr["outcome"]
    ok = out == SUCCESS
    danger = lambda c: ((c >= 0) & (c < cfg.danger_dist) & act).sum(0)
    agent_danger = danger(tr["agent_clearance"])
    path = ((tr["xy"][1:] - tr["xy"][:-1]).norm(dim=-1) * act).sum(0).double()
    ratio = path / (tr["goal"] - tr["start"]).norm(dim=-1).double()
    min_agent = torch.where(act, tr["agent_clearance"].double(), math.inf).amin(0).clamp_max(cfg.sensing_range)
    per_agent = {f"{name}_rate": out == code for code, name in OUTCOMES.items()} | {
        "nav_time_s": steps[ok] * cfg.dt,
        "path_length_ratio": ratio[ok],
        "agent_dangers_per_agent": agent_danger.double(),
        "dangers_per_agent": danger(tr["clearance"]).double(),
        "min_agent_clearance": min_agent,
    }
    all_ok = ok.all(-1)
    ep_time = steps.amax(-1) * cfg.dt
    per_episode = {
        "all_arrived_rate": all_ok,
        "any_collision_rate": (out == COLLISION).any(-1),
        "collisions_per_episode": (out == COLLISION).sum(-1).double(),
        "colliding_pairs_per_episode": tr["pairs"].triu(1).sum((-1, -2)).double(),
        "agent_dangers_per_episode": agent_danger.sum(-1).double(),
        "episode_time_s": ep_time[all_ok],
    }
    res = {k: summarise(metric(k), x.flatten()) for k, x in per_agent.items()}
    res["episode"] = {k: summarise(metric(k), x.flatten()) for k, x in per_episode.items()}
    return res


def settings(cfg: SelfPlayConfig, scenarios=("circle", "square"), n_agents=None) -> dict[str, SelfPlayConfig]:
    """Each evaluated scenario x agent count's config; one that cannot be placed is a ValueError naming it."""
    counts = [cfg.n_agents] if n_agents is None else [int(n) for n in n_agents]
    return {f"{scenario}_n{n}": SelfPlayConfig(**{**asdict(cfg), "scenario": scenario, "n_agents": n})
            for scenario in scenarios for n in counts}


def evaluate_selfplay(policy: Policy, cfg: SelfPlayConfig, scenarios=("circle", "square"), n_agents=None,
                      episodes: int = 100, seed: int = 0, out_dir: Path | None = None, meta: dict | None = None) -> dict:
    """Evaluate ``policy`` on the seeded self-play set of every scenario x agent count; optionally write results."""
    results = {"protocol": PROTOCOL, "policy": policy.name, "meta": meta or {}, "episodes": episodes,
               "seed": seed, "settings": {}}
    for name, c in settings(cfg, scenarios, n_agents).items():
        eps = episode_set(c, episodes, seed)
        tr = rollout(policy, c, eps)
        results["settings"][name] = metrics(tr, c)
        results["sim_config"] = {k: v for k, v in asdict(c).items() if k not in ("scenario", "n_agents")}
    if out_dir is not None:
        write_results(Path(out_dir), results)  # atomic: a failed write leaves no half results.json
    return results


def evaluate_setting(policy: Policy, cfg: SelfPlayConfig, setting: str, episodes: int | None = None,
                     out_dir: Path | None = None, meta: dict | None = None, save_episodes: bool = True) -> dict:
    """A leaderboard track: ``policy`` on the published list of ``setting`` (its first ``episodes``, if given).

    The results hold the per-agent and the per-episode metrics side by side under ``scenes[setting]`` (the
    leaderboard's layout; their keys differ); ``episodes.jsonl`` has one line per episode, its outcome
    (every agent arrived: success; else any collision: collision; else timeout) and each agent's."""
    from crowdbench.protocols.lists import check_selfplay

    saved, digest = check_selfplay(setting, list_path(setting))
    eps = episodes_of(saved, cfg, episodes)
    tr = rollout(policy, cfg, eps)
    m = metrics(tr, cfg)
    results = {"protocol": PROTOCOL, "policy": policy.name, "meta": meta or {}, "episodes": len(eps["start"]),
               "seed": saved["seed"], "scenes": {setting: {**{k: v for k, v in m.items() if k != "episode"},
                                                           **m["episode"]}},
               "lists": {setting: digest}, "sim_config": {k: v for k, v in asdict(cfg).items() if k != "frame"}}
    rows = []
    for e, out in enumerate(tr["outcome"].tolist()):
        worst = SUCCESS if all(o == SUCCESS for o in out) else COLLISION if COLLISION in out else TIMEOUT
        rows.append({"protocol": PROTOCOL, "setting": setting, "episode": e, "outcome": OUTCOMES[worst],
                     "agent_outcomes": "".join(OUTCOME_CHAR[o] for o in out)})
    if out_dir is not None:
        write_results(Path(out_dir), results, rows if save_episodes else None)
    return results


def format_table(results: dict) -> str:
    """The means of the self-play table's metrics (crowdbench/metric_table.py), one row per setting."""
    cols = in_table(IN_SELFPLAY)
    head = f"{'setting':<12}" + "".join(f"{m.column:>15}" for m in cols)
    lines = [(f"policy: {results['policy']}  protocol: {results['protocol']} ({results['episodes']} episodes, "
             f"seed {results['seed']}); rates per agent except 'all arrived'"), head]
    for name, r in results["settings"].items():
        vals = [(r[m.key] if m.key in r else r["episode"][m.key])["mean"] for m in cols]
        lines.append(f"{name:<12}" + "".join(f"{'n/a' if v is None else f'{v:.3f}':>15}" for v in vals))
    return "\n".join(lines)


def _evaluated(env_cfg) -> tuple[list[str], list[int] | None]:
    """``env.eval_scenarios`` and ``env.eval_n_agents`` (None: the training count) as :func:`settings` takes them."""
    counts = env_cfg.eval_n_agents
    return list(env_cfg.eval_scenarios), None if counts is None else list(counts)


class SelfPlayProtocol(Protocol):
    """Every agent acts from the policy (a robot checkpoint too: the transfer test). Its tracks
    (crowdbench/protocols/selfplay_tracks.py) take the baselines that act for every agent (ORCA, straight)
    and the entries trained in self-play; robot entries are not evaluated there (docs/selfplay.md,
    "Leaderboard tracks"). Its training probe is protocol v1's: a self-play policy is also a robot policy."""

    name, label, world, command = "selfplay", PROTOCOL, "selfplay", "eval-selfplay"
    tracks = tuple(Track(track_name(s), title, "selfplay", setting=s) for s, title in SETTINGS)
    home = HOME
    privileged_ok = False  # the oracle plans against replayed humans, not against agents that react
    danger_metric = "agent_dangers_per_agent"
    oracle_note = "The oracle does not apply: every agent reacts to the others, so their future is not known in advance."

    def selects(self, env_cfg) -> bool:
        return env_name(env_cfg) == self.world

    def check(self, cfg, policy_name: str) -> None:
        from crowdbench.policies import BASELINES, PRIVILEGED

        if policy_name in PRIVILEGED:
            raise ValueError(f"the {policy_name} plans against replayed humans, not reacting agents: not available "
                             f"with env=selfplay; valid: {', '.join(BASELINES)} or a checkpoint path")

    def check_run(self, cfg) -> None:
        """Every ``env.eval_scenarios`` x ``env.eval_n_agents`` setting can be placed: checked before training, so
        that e.g. 32 agents on the default 8 m square fail at once, not after a 30-minute run."""
        try:
            settings(selfplay_config(cfg.env, frame="rotate"), *_evaluated(cfg.env))
        except ValueError as err:
            raise ValueError(f"env.eval_n_agents / env.eval_scenarios: {err}") from None

    def run(self, policy, cfg, out: Path, overrides: list[str], strict: bool = True, progress=None) -> dict:
        e = cfg.env
        return evaluate_selfplay(policy, selfplay_config(e, frame=policy.frame), *_evaluated(e), int(e.eval_episodes),
                                 int(e.eval_seed), out_dir=out, meta={"seed": cfg.seed, "overrides": overrides})

    def format_table(self, results: dict) -> str:
        return format_table(results)

    def probe(self, cfg):
        from crowdbench.protocols.replay import replay_probe

        return replay_probe(cfg, None)

    # ------------------------------------------------------------------ leaderboard
    def admits(self, kind: str, trained_on: str | None) -> bool:
        # why not robot entries as transfer: ~40 of them on 9 tracks of up to 3,200 agents a step would cost
        # hours per run for numbers `crowdbench eval env=selfplay policy=RUN/checkpoint.pt` gives on demand
        return kind == "baseline" or (kind == "learned" and trained_on in (HOME, *(t.name for t in self.tracks)))

    def trained_track(self, env: dict) -> str | None:
        return HOME

    def evaluate_track(self, track: Track, policy, scenes: list[str], episodes: int | None, out_dir, meta: dict,
                       env=None, save_episodes: bool = True) -> dict:
        cfg = self.sim_config(env, frame=policy.frame)
        return evaluate_setting(policy, cfg, track.setting, episodes, out_dir, meta, save_episodes)

    short = "self-play"

    def where(self, track: Track) -> str:
        return (f"the {EPISODES} episodes of the published list {track.setting}, rates per agent (all arrived, any "
                "collision: per episode)")

    def track_overrides(self, track: Track) -> tuple[str, ...]:
        return setting_overrides(track.setting)

    def list_files(self, track: Track, scenes: list[str]) -> list[Path]:
        return [list_path(track.setting)]

    def check_lists(self, scenes: list[str]) -> None:
        from crowdbench.protocols.lists import check_selfplay

        for t in self.tracks:
            check_selfplay(t.setting, list_path(t.setting))

    def check_results(self, results: dict) -> None:
        from crowdbench.protocols.lists import SELFPLAY, ListError

        for setting, digest in results.get("lists", {}).items():
            if SELFPLAY.get(setting) != digest:
                raise ListError(f"self-play setting {setting}: list digest {str(digest)[:12]}... is not the published one")
