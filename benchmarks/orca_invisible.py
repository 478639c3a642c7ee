"""ORCA's parameters for a robot the humans do not see, on CrowdNav's validation cases (never the test cases).

    python benchmarks/orca_invisible.py                          # circle_n5 and square_n5, the default grid
    python benchmarks/orca_invisible.py --settings circle_n20 --margins 0.2,0.3 --horizons 8

Prints success / collision / timeout / navigation time of the ORCA robot (``policy=orca`` with
``env=crowdnav``'s settings but ``orca.safety_margin`` and ``orca.time_horizon``) on each setting's 100
validation cases, one row per (margin, horizon). The baseline submission ``orca_invisible`` and
``experiment=crowdnav_residual`` use the setting chosen here (docs/crowdnav.md, "ORCA for an invisible robot").
"""

from __future__ import annotations

import argparse
import time

import torch


def evaluate(setting: str, margin: float, horizon: float) -> dict:
    from crowdbench.app import protocol_of
    from crowdbench.baselines.orca import ORCA
    from crowdbench.cli import compose
    from crowdbench.protocols.crowdnav import evaluate_crowdnav

    scenario, n = setting.split("_n")
    cfg = compose(["env=crowdnav", f"env.scenario={scenario}", f"env.n_humans={n}",
                   f"orca.safety_margin={margin}", f"orca.time_horizon={horizon}"])
    sim = protocol_of(cfg).sim_config(cfg.env)
    res = evaluate_crowdnav(ORCA.from_config(cfg), sim, [setting], 100, phase="val")["scenes"][setting]
    return {k: res[k]["mean"] for k in ("success_rate", "collision_rate", "timeout_rate", "nav_time_s")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--settings", default="circle_n5,square_n5")
    ap.add_argument("--margins", default="0.02,0.1,0.2,0.3,0.4,0.5,0.7", help="m added to every human's radius")
    ap.add_argument("--horizons", default="2,5,8,12", help="s")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print("| setting | margin (m) | horizon (s) | success | collision | timeout | nav time (s) |")
    print("|---|---|---|---|---|---|---|")
    t0 = time.perf_counter()
    for setting in args.settings.split(","):
        for margin in map(float, args.margins.split(",")):
            for horizon in map(float, args.horizons.split(",")):
                r = evaluate(setting, margin, horizon)
                print(f"| {setting} | {margin:g} | {horizon:g} | {r['success_rate']:.2f} | {r['collision_rate']:.2f} | "
                      f"{r['timeout_rate']:.2f} | {r['nav_time_s']:.2f} |", flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
