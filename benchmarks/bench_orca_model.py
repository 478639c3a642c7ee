"""Batched torch ORCA (crowdbench.envs.humans.orca): agreement with RVO2 and speed.

(a) Agreement with RVO2 (pyrvo) on random worlds of several kinds (sparse, dense,
    overlapping discs, infeasible LPs): the fraction of agents whose new velocity is within
    1e-3 m/s (max abs component), and for the others whether our answer is an equally valid
    ORCA solution (same largest half-plane penetration as RVO2's, inside the speed disc).
(b) Time per call and world-steps/s for N worlds of K agents on a circle-crossing crowd,
    timed along a short rollout (so velocities are ORCA's own, as in the simulator), with
    this benchmark's parameters or (``--crowdnav``) CrowdNav's human parameters (time horizon
    5 s, neighbour distance 10 m, radius 0.31 m: everybody meets in the centre and
    linearProgram3 runs for up to half of the agents). The load average is printed with the
    figures: on a shared machine, compare only numbers taken under similar load.

    PYTHONPATH=. python benchmarks/bench_orca_model.py [--worlds 1250] [--agents 10]
        [--n 1024] [--ks 6 21 51] [--threads 1 2] [--steps 12] [--crowdnav] [--no-agreement]
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from crowdbench.envs.humans.lp import linear_program2
from crowdbench.envs.humans.orca import orca_lines, orca_velocities
from crowdbench.envs.humans.rvo2_reference import KINDS, random_configs, rvo2_velocities

PARAMS = {"time_horizon": 2.0, "dt": 0.25, "neighbor_dist": 4.0, "max_neighbors": 6}


def _penetration(lines, v):
    px, py, dx, dy, exists = lines
    d = dx * (py - v[:, 1:2]) - dy * (px - v[:, 0:1])
    return torch.where(exists, d, -math.inf).amax(dim=1).clamp_min(0.0)


def agreement(worlds: int, agents: int) -> None:
    print(f"(a) agreement with RVO2: {worlds} worlds x up to {agents} agents per kind, {PARAMS}")
    total = close_total = 0
    for s, kind in enumerate(KINDS):
        cfg = random_configs(kind, worlds, agents, seed=100 + s)
        ours = orca_velocities(**cfg, **PARAMS)
        ref = torch.from_numpy(rvo2_velocities(**cfg, **PARAMS))
        valid = cfg["valid"].reshape(-1)
        ours, ref = ours.reshape(-1, 2)[valid], ref.reshape(-1, 2)[valid]
        lines = [x[valid] for x in orca_lines(cfg["pos"], cfg["vel"], cfg["valid"], cfg["radius"], **PARAMS)]
        speed = cfg["max_speed"].reshape(-1)[valid]
        pref = cfg["pref"].reshape(-1, 2)[valid]
        _, _, fail = linear_program2(*lines, speed, pref[:, 0], pref[:, 1], False)
        lp3 = fail < lines[0].shape[1]
        diff = (ours - ref).abs().amax(dim=1)
        close = diff <= 1e-3
        far = ~close
        total += diff.numel()
        close_total += int(close.sum())
        pen_o, pen_r = _penetration(lines, ours), _penetration(lines, ref)
        print(
            f"  {kind:10s} agents {diff.numel():6d}  LP3 {lp3.float().mean():6.1%}  within 1e-3: "
            f"{close.float().mean():8.4%}  median diff {diff.median():.1e}  max diff {diff.max():.3g}"
        )
        if far.any():
            dp = (pen_o[far] - pen_r[far]).abs()
            print(
                f"    {int(far.sum())} disagreements: {int(lp3[far].sum())} in LP3; "
                f"|max penetration ours - RVO2| max {dp.max():.1e}; "
                f"ours further out of the speed disc than RVO2: {int((ours[far].norm(dim=1) > torch.maximum(speed[far], ref[far].norm(dim=1)) * (1 + 1e-4)).sum())}; "
                f"RVO2 |v| - max_speed in [{(ref[far].norm(dim=1) - speed[far]).min():.1e}, "
                f"{(ref[far].norm(dim=1) - speed[far]).max():.1e}]"
            )
        feas = ~lp3
        print(f"    LP2-feasible agents: our max penetration {pen_o[feas].max():.1e} (0 = inside every half-plane)")
    print(f"  overall: {close_total}/{total} = {close_total / total:.4%} within 1e-3 m/s")


def crowd(n: int, k: int, seed: int = 0):
    """Circle crossing: K agents near a 4 m circle (random angles), goals opposite."""
    g = torch.Generator().manual_seed(seed)
    ang = torch.rand(n, k, generator=g, dtype=torch.float64) * 2 * math.pi
    pos = 4.0 * torch.stack([ang.cos(), ang.sin()], -1)
    pos = pos + 0.05 * torch.randn(n, k, 2, generator=g, dtype=torch.float64)
    return pos, -pos


def _load() -> str:
    with open("/proc/loadavg") as f:
        return " ".join(f.read().split()[:3])


def timing(n: int, ks, threads, steps: int, crowdnav: bool = False) -> None:
    if crowdnav:
        params = {"time_horizon": 5.0, "dt": 0.25, "neighbor_dist": 10.0, "max_neighbors": 10}
        radius = 0.31
    else:
        params = {"time_horizon": 2.0, "dt": 0.25, "neighbor_dist": 5.0, "max_neighbors": 10}
        radius = 0.3
    print(f"(b) time per call, N={n}, circle crossing, radius {radius}, max_speed 1, {steps} timed steps, {params}")
    for nt in threads:
        torch.set_num_threads(nt)
        for k in ks:
            pos, goal = crowd(n, k)
            vel = torch.zeros_like(pos)
            valid = torch.ones(n, k, dtype=torch.bool)
            times = []
            for step in range(steps + 2):
                d = goal - pos
                pref = d / d.norm(dim=-1, keepdim=True).clamp_min(1.0)
                t0 = time.perf_counter()
                vel = orca_velocities(pos, vel, pref, valid, radius, 1.0, **params)
                if step >= 2:  # the first calls pay for allocations
                    times.append(time.perf_counter() - t0)
                pos = pos + vel * 0.25
            times.sort()
            med = times[len(times) // 2]
            print(
                f"  threads {nt}  K={k:3d}: median {med * 1e3:7.1f} ms  (min {times[0] * 1e3:7.1f})  "
                f"{n / med:9.0f} world-steps/s  (load {_load()})"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", type=int, default=1250, help="random worlds per kind (4 kinds)")
    ap.add_argument("--agents", type=int, default=10)
    ap.add_argument("--n", type=int, default=1024)
    ap.add_argument("--ks", type=int, nargs="+", default=[6, 21, 51])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--crowdnav", action="store_true", help="CrowdNav's human ORCA parameters")
    ap.add_argument("--no-agreement", action="store_true", help="timing only")
    args = ap.parse_args()
    if not args.no_agreement:
        agreement(args.worlds, args.agents)
    timing(args.n, args.ks, args.threads, args.steps, args.crowdnav)


if __name__ == "__main__":
    main()
