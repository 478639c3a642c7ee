"""The privileged oracle's success against its search effort on a CrowdNav setting (docs/crowdnav.md, "Oracle").

    python benchmarks/oracle_effort.py                                   # circle 20: the 16 cases beam 128 fails
    python benchmarks/oracle_effort.py --cases all --searches "beam=128"
    python benchmarks/oracle_effort.py --searches "beam=512;beam=512,speeds=1/0.75/0.5/0.25,headings=32"

Each search is a set of oracle settings (``beam``, ``headings``, ``speeds`` as ``/``-separated fractions of
``v_max``, ``cell``); the rest are ``env=crowdnav``'s. For each it plans the chosen test cases against the
humans' future (simulated once without the robot, as the harness does) and prints how many plans reach the
goal, the wall time and the cases still failed. The planned outcome is the executed one (tests/test_oracle.py
checks it), so no rollout is needed to count successes. ``--cases``: a comma-separated list of case ids (the
default: the 16 circle-20 cases beam 128 fails, found with ``--cases all --searches beam=128``); ``all``, the 500
test cases; ``failed``, the cases the committed oracle row fails (``leaderboard/results/oracle/<track>.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
BEAM_128_FAILS = "10,76,117,120,147,176,190,205,232,265,311,317,318,416,474,496"  # circle 20's test cases
DEFAULT_SEARCHES = ("beam=128;beam=512;beam=2048;beam=512,speeds=1/0.75/0.5/0.25;"
                    "beam=512,headings=32;beam=2048,speeds=1/0.75/0.5/0.25,headings=32")


def parse_search(text: str, base: dict) -> dict:
    """``"beam=512,speeds=1/0.5"`` -> the oracle's keyword arguments on top of ``base``."""
    out = dict(base)
    for part in filter(None, text.split(",")):
        key, _, value = part.partition("=")
        key = key.strip()
        if key not in ("beam", "headings", "speeds", "cell", "danger_cost", "chunk"):
            raise SystemExit(f"--searches: unknown oracle key {key!r} in {text!r}")
        out[key] = [float(v) for v in value.split("/")] if key == "speeds" else type(base[key])(value)
    return out


def case_ids(which: str, track: str, n_cases: int) -> list[int]:
    if which == "all":
        return list(range(n_cases))
    if which == "failed":
        saved = json.loads((ROOT / "leaderboard" / "results" / "oracle" / f"{track}.json").read_text())
        scene = next(iter(saved["unavoidable"].values()))
        failed = sorted(scene["collision"] + scene["timeout"])
        if not failed:
            raise SystemExit(f"--cases failed: the committed oracle row fails no case of {track}")
        return failed
    return [int(c) for c in which.split(",")]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="circle", choices=("circle", "square"))
    ap.add_argument("--humans", type=int, default=20)
    ap.add_argument("--cases", default=BEAM_128_FAILS, help="comma-separated case ids | all | failed")
    ap.add_argument("--searches", default=DEFAULT_SEARCHES, help="';'-separated oracle settings")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    from crowdbench.baselines.oracle import PLANNED_SUCCESS, Oracle
    from crowdbench.baselines.params import params
    from crowdbench.cli import compose
    from crowdbench.envs.crowdnav import CrowdNavScenario
    from crowdbench.envs.factory import crowdnav_world, sim_config
    from crowdbench.protocols.crowdnav import future_view

    cfg = compose(["env=crowdnav", f"env.scenario={args.scenario}", f"env.n_humans={args.humans}"])
    sim = replace(sim_config(cfg.env), frame=Oracle.frame)
    full = CrowdNavScenario(sim).test_list()
    track = f"crowdnav-{args.scenario}{args.humans}"
    ids = case_ids(args.cases, track, len(full["case"]))
    keep = torch.tensor(ids, dtype=torch.long)
    eps = {k: v[keep] for k, v in full.items()}
    world, _ = crowdnav_world(sim, len(ids))
    world.reset(torch.ones(len(ids), dtype=torch.bool), eps)
    view = future_view(world, sim, eps)
    base = params("oracle", cfg)
    print(f"{track}: {len(ids)} test cases ({args.cases}); oracle defaults {base}; {args.threads} thread(s), "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"{'search':58s} {'success':>9s} {'seconds':>8s}  failed cases")
    for text in args.searches.split(";"):
        kw = parse_search(text, base)
        oracle = Oracle(**kw)
        t = time.perf_counter()
        oracle.plan(view)
        secs = time.perf_counter() - t
        ok = oracle.planned_outcome == PLANNED_SUCCESS
        failed = [c for c, s in zip(ids, ok.tolist(), strict=True) if not s]
        print(f"{text:58s} {int(ok.sum()):4d}/{len(ids):<4d} {secs:8.1f}  {failed}")


if __name__ == "__main__":
    main()
