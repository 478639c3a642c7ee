"""The evaluation engine the protocols share: roll a policy out over a fixed episode set in the batched
world, turn the traces into per-episode values, aggregate them with their 95% intervals
(crowdbench/metric_table.py) and write the results files atomically.

All episodes of a setting run in one batched simulator (``B`` = number of episodes), so a policy is
called once per time step for the whole list. Metric definitions: docs/protocol.md. The protocols
(:mod:`crowdbench.protocols`) choose the episodes, the world and the layout of results.json.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from crowdbench.envs.lookahead import lookahead_observation
from crowdbench.envs.observation import ACTION, OBS, Policy
from crowdbench.envs.protocol import PAPER_SCENES, PROTOCOL_VERSION
from crowdbench.envs.rules import OUTCOMES, RUNNING, SUCCESS, SimConfig
from crowdbench.envs.torchrl_env import CrowdEnv
from crowdbench.metric_table import (
    ANY,
    IN_TRACKS,
    Z95,
    Metric,
    clip,
    columns,
    half_width,
    of_protocol,
    within,
)
from crowdbench.social_metrics import episode_social_metrics

PERSONAL_SPACE = 0.45  # m, surface gap


def mean_ci(x: torch.Tensor, bounds: tuple[float, float] = ANY) -> dict:
    """Mean with a normal-approximation 95% interval (``n`` >= 30 in the protocol) clipped to ``bounds``, the
    metric's range, and the sample standard deviation ``sd``: the leaderboard's statistics read the
    standard error from it (:func:`crowdbench.metric_table.spread`), which a clipped interval no longer shows."""
    x = x.double()
    n = x.numel()
    if n == 0:
        return {"mean": None, "ci95": [None, None], "n": 0, "sd": None}
    m = x.mean().item()
    sd = x.std().item() if n > 1 else None
    h = half_width(sd, n)
    return {"mean": m, "ci95": list(within(bounds, m - h, m + h)), "n": n, "sd": sd}


def rate_ci(k: int, n: int) -> dict:
    """Proportion with the Wilson score 95% interval (well-behaved at 0 and 1)."""
    if n == 0:
        return {"mean": None, "ci95": [None, None], "n": 0}
    p = k / n
    den = 1 + Z95**2 / n
    centre = (p + Z95**2 / (2 * n)) / den
    half = Z95 * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n)) / den
    return {"mean": p, "ci95": [max(0.0, centre - half), min(1.0, centre + half)], "n": n}


def summarise(metric: Metric, x: torch.Tensor) -> dict:
    """``metric``'s entry of results.json from its values ``x`` (one per episode, or per agent): a rate
    with its Wilson interval, or a mean with its normal interval clipped to the metric's range."""
    if metric.interval == "wilson":
        return rate_ci(int(x.sum()), x.numel())
    return mean_ci(x, metric.range)


def select_episodes(saved: dict, n: int | None) -> list[dict]:
    """The whole list, or ``n`` episodes evenly strided over it (not the official protocol)."""
    eps = saved["episodes"]
    if n is None or n >= len(eps):
        return eps
    if n < 1:
        raise ValueError(f"eval.episodes must be >= 1, got {n}")
    idx = torch.linspace(0, len(eps) - 1, n).round().long().unique()
    return [eps[i] for i in idx.tolist()]


@torch.no_grad()
def privilege_labels(policy: Policy) -> dict:
    """What a results file says about what ``policy`` was handed: ``privileged`` (the oracle's plan from the
    humans' future, or a value lookahead reading the simulator's next human states) and ``lookahead`` (the
    humans' next-state model of a value-lookahead policy's candidates)."""
    out = {"privileged": True} if getattr(policy, "privileged", False) else {}
    look = getattr(policy, "lookahead", None)
    if look is not None:
        out["lookahead"] = look[0]
        if getattr(policy, "privileged_lookahead", False):
            out["privileged"] = True
    return out


def drive(env: CrowdEnv, policy: Policy, recorder=None, on_reset=None, on_step=None, privileged_view=None) -> None:
    """The evaluation loop of every protocol: reset ``env`` (its fixed episode list, one episode per
    environment), then step it with ``policy`` until every agent is done or the time limit.

    ``on_reset(world)`` sees the start state, ``on_step(world, info)`` collects traces after every step;
    ``recorder(world, td, action)`` (e.g. :class:`crowdbench.viz.record.SceneRecorder`), if given, is
    called before every step, its optional ``after_step(world, info)`` after it and ``close()`` at the end. Finished episodes stay frozen
    (no reset), so episode ``i`` of the list is environment ``i`` throughout. A privileged policy (the
    oracle) plans from ``privileged_view`` (default: the world, whose replayed scene is the future).
    """
    world = env.world
    td = env.reset()
    everyone = torch.ones(world.B, dtype=torch.bool)
    policy.reset(everyone)
    if getattr(policy, "privileged", False):  # the oracle: plans from the scene's future (docs/protocol.md, "Oracle")
        policy.plan(world if privileged_view is None else privileged_view)
    if on_reset is not None:
        on_reset(world)
    look = getattr(policy, "lookahead", None)  # (model, actions): a value-lookahead policy (crowdbench/algos/value.py)
    for _ in range(world.cfg.time_limit):
        obs = td.select(OBS)
        if look is not None:  # the candidates are computed here, on the harness side, from the world
            for key, value in lookahead_observation(world, look[1], look[0]).items():
                obs.set(OBS + (key,), value)
        action = policy.act(obs)
        if recorder is not None:
            recorder(world, obs, action)
        td.set(ACTION, action)
        td = env.step(td).get("next")
        info = env.last_info
        if recorder is not None and hasattr(recorder, "after_step"):
            recorder.after_step(world, info)
        if on_step is not None:
            on_step(world, info)
        if not (world.outcome == RUNNING).any():
            break
    if recorder is not None and hasattr(recorder, "close"):
        recorder.close()


def robot_traces(env: CrowdEnv, policy: Policy, recorder=None, privileged_view=None) -> dict:
    """Traces ``[T, B]`` of robot 0 of every environment of ``env`` driven by ``policy``."""
    world = env.world
    xy, clear, swept, reward, active = [], [], [], [], []
    reactive = hasattr(world.crowd, "offset")  # protocol v2: how far the robot pushed the humans off their tracks
    offset, deviation = [], []
    hxy, hvel, hpresent = [], [], []  # the humans at every step's end (time-to-collision)

    def on_step(w, info):
        xy.append(w.pos[:, 0].clone())
        h = w.humans()
        hxy.append(h[0].clone())
        hvel.append(h[1].clone())
        hpresent.append(h[2].clone())
        clear.append(info.clearance[:, 0])
        swept.append(info.swept_clearance[:, 0])
        reward.append(info.reward[:, 0])
        active.append(info.active[:, 0])
        if reactive:
            present = w.humans()[2]
            offset.append((w.crowd.offset.norm(dim=-1) * present).amax(-1) if w.Mh else torch.zeros(w.B))
            deviation.append((w.crowd.dev.norm(dim=-1) * present).sum(-1) * w.cfg.dt)

    first = {}

    def on_reset(w):
        first.update(xy=w.pos[:, 0].clone(), clearance0=w.min_clearance()[:, 0])

    drive(env, policy, recorder, on_reset, on_step, privileged_view)
    traces = {
        "xy": torch.stack([first["xy"], *xy]), "clearance": torch.stack(clear), "swept": torch.stack(swept),
        "reward": torch.stack(reward), "active": torch.stack(active), "outcome": world.outcome[:, 0].clone(),
        "clearance0": first["clearance0"], "start": world.start[:, 0], "goal": world.goal[:, 0],
        "humans_xy": torch.stack(hxy), "humans_vel": torch.stack(hvel), "humans_present": torch.stack(hpresent),
    }
    if reactive:
        traces.update(crowd_offset=torch.stack(offset), crowd_deviation=torch.stack(deviation))
    return traces


def episode_metrics(tr: dict, cfg: SimConfig, gamma: float = 0.99) -> dict[str, torch.Tensor]:
    """Per-episode metrics ``[B]`` from traces (inactive steps are ignored)."""
    act = tr["active"].double()  # [T, B]
    steps = act.sum(0)
    clear = tr["clearance"].double()
    in_danger = (clear >= 0) & (clear < cfg.danger_dist) & tr["active"]
    prev = torch.cat([((tr["clearance0"] >= 0) & (tr["clearance0"] < cfg.danger_dist)).unsqueeze(0), in_danger[:-1]])
    vel = (tr["xy"][1:] - tr["xy"][:-1]).double() / cfg.dt  # [T, B, 2]
    vel_prev = torch.cat([torch.zeros_like(vel[:1]), vel[:-1]])
    acc = (vel - vel_prev) / cfg.dt
    acc_prev = torch.cat([torch.zeros_like(acc[:1]), acc[:-1]])
    jerk = ((acc - acc_prev) / cfg.dt).norm(dim=-1) * act
    path = ((tr["xy"][1:] - tr["xy"][:-1]).double().norm(dim=-1) * act).sum(0)
    success = tr["outcome"] == SUCCESS
    discount = gamma ** torch.arange(act.shape[0], dtype=torch.float64).unsqueeze(1)
    straight = (tr["goal"] - tr["start"]).double().norm(dim=-1)
    crowd = {}
    if "crowd_offset" in tr:  # protocol v2
        crowd = {"crowd_offset_max": (tr["crowd_offset"].double() * act).amax(0),
                 "crowd_deviation": (tr["crowd_deviation"].double() * act).sum(0)}
    metrics = crowd | {
        "outcome": tr["outcome"],
        "steps": steps,
        "nav_time": steps * cfg.dt,
        "danger_steps": in_danger.sum(0),
        "danger_events": (in_danger & ~prev).sum(0),
        # capped at the sensing range: an episode with nobody within 5 m reports 5.0
        "min_clearance": torch.where(tr["active"], tr["swept"].double(), math.inf).amin(0).clamp_max(cfg.sensing_range),
        "path_length": path,
        "path_ratio": path / straight,
        "mean_speed": path / (steps * cfg.dt).clamp_min(1e-9),
        "jerk": jerk.sum(0) / steps.clamp_min(1),
        "personal_space": ((clear >= PERSONAL_SPACE) & tr["active"]).sum(0) / steps.clamp_min(1),
        "return": (tr["reward"].double() * discount).sum(0),
        "success": success,
    }
    # the field's social-navigation metrics (crowdbench/social_metrics.py): new keys only
    return metrics | episode_social_metrics(tr, cfg, success, path, steps * cfg.dt)


def aggregate(m: dict[str, torch.Tensor], protocol: str = PROTOCOL_VERSION) -> dict:
    """Every metric of ``protocol`` in crowdbench/metric_table.py from the per-episode values ``m``, laid
    out as results.json always was: the rates, then the means over the successful episodes, then those
    over every episode (failed ones included), each in the table's order."""
    values = m | {name: m["outcome"] == code for code, name in OUTCOMES.items()}
    ok = m["success"]
    out = {}
    for metric in sorted(of_protocol(protocol), key=lambda x: (x.interval != "wilson", not x.successful_only)):
        x = values[metric.source or metric.key]
        out[metric.key] = summarise(metric, x[ok] if metric.successful_only else x)
    return out


def write_results(out_dir: Path, results: dict, rows: list[dict] | None = None) -> None:
    """``results.json`` and, with ``rows``, ``episodes.jsonl`` (one episode per line) in ``out_dir``."""
    from crowdbench.outputs import write_text_atomic

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # results.json last, each file whole or not at all: a write that fails (a full disk) leaves no
    # results.json, which would make a retry refuse the directory
    if rows is not None:
        write_text_atomic(out_dir / "episodes.jsonl", "".join(json.dumps(r) + "\n" for r in rows))
    write_text_atomic(out_dir / "results.json", json.dumps(results, indent=1) + "\n")


def format_table(results: dict) -> str:
    """A plain-text table, one row per scene, of the metrics of TRACKS.md's columns that the results hold;
    then, in a second table, the optional ones (the social-navigation metrics): results written before
    them print the first table as they always did."""
    shown = columns(IN_TRACKS, [results])
    cols = [(m.key, m.column) for m in shown if not m.optional]
    w = 24  # fits "10.620 [10.156,11.085]"
    tag = "  [PRIVILEGED: knows the humans' future; an upper bound]" if results.get("privileged") else ""
    tag += f"  humans: reactive {results['humans']}" if "humans" in results else ""
    lines = [f"policy: {results['policy']}  protocol: {results['protocol']}{tag}", *_table_rows(results, cols, w)]
    if "average_paper_scenes" in results:
        a = results["average_paper_scenes"]
        lines.append(f"{'avg (paper)':<13}" + "".join(f"{'n/a' if a[k] is None else f'{a[k]:.3f}':>{w}}"
                                                      for k, _ in cols if k in a))
    later = [(m.key, m.column) for m in shown if m.optional]
    if later:
        lines += ["", *_table_rows(results, later, w)]
    return "\n".join(lines)


def _table_rows(results: dict, cols: list[tuple[str, str]], w: int) -> list[str]:
    lines = [f"{'scene':<13}" + "".join(f"{name:>{w}}" for _, name in cols)]
    for scene, r in results["scenes"].items():
        cells = []
        for key, _ in cols:
            v = r.get(key)
            cells.append("n/a" if not v or v["mean"] is None else
                         "{:.3f} [{:.3f},{:.3f}]".format(v["mean"], *clip(key, *v["ci95"])))
        lines.append(f"{scene:<13}" + "".join(f"{c:>{w}}" for c in cells))
    return lines


def markdown_table(runs: list[dict], metric: str = "success_rate", digits: int = 3) -> str:
    """Markdown table of one metric: a row per results dict, a column per scene (+ paper-scene average)."""
    scenes = list(dict.fromkeys(s for r in runs for s in r["scenes"]))
    paper = [s for s in PAPER_SCENES if s in scenes]
    head = ["policy", *scenes] + (["avg (paper scenes)"] if paper else [])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in runs:
        cells = [r["policy"]]
        for s in scenes:
            v = r["scenes"].get(s, {}).get(metric)
            lo, hi = clip(metric, *v["ci95"]) if v and v["mean"] is not None else (None, None)
            cells.append("—" if lo is None else f"{v['mean']:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]")
        if paper:
            vals = [r["scenes"][s][metric]["mean"] for s in paper if s in r["scenes"]]
            cells.append(f"{sum(vals) / len(vals):.{digits}f}" if len(vals) == len(paper) and None not in vals else "—")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
