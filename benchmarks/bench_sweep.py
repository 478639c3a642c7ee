"""What a sweep engine costs: the same 3-seed sweep run sequentially (Hydra's basic launcher), with the
joblib and Ray launchers (2 workers), and as two processes started by hand (``xargs -P 2``, no engine).

    python benchmarks/bench_sweep.py [--frames 4096] [--out /tmp/bench_sweep]

Each run is one row of ``experiment=leaderboard_scratch`` (MP-GatedGCN-RL, TD3) at a reduced budget. Prints the
wall time of each mode, the engine's overhead against the hand-started processes, and Ray's start-up
costs (starting a local cluster; the first and a later empty task, which include starting a worker
process). Run it with nothing else running on the machine: the modes compete for the same cores.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

SEEDS = (0, 1, 2)


def recipe(frames: int) -> list[str]:
    return ["experiment=leaderboard_scratch", "method=gatedgcn_td3", f"train.total_frames={frames}", "eval.episodes=50",
            "train.probe_every=1000000"]


def timed(cmd: list[str], env: dict) -> float:
    t = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def successes(sweep_dir: Path) -> list[float]:
    return [r["success"] for r in json.loads((sweep_dir / "sweep.json").read_text())["runs"]]


def ray_startup() -> tuple[float, float, float]:
    import ray

    t = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=100 * 1024 ** 2)
    started = time.perf_counter() - t

    @ray.remote(num_cpus=1)
    def nothing():
        return 0

    t = time.perf_counter()
    ray.get(nothing.remote())
    first = time.perf_counter() - t
    t = time.perf_counter()
    ray.get(nothing.remote())
    later = time.perf_counter() - t
    ray.shutdown()
    return started, first, later


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=4096)
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_sweep"))
    args = ap.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RL_WARNINGS": "False", "RAY_AUTH_MODE": "disabled"}
    cli = [sys.executable, "-m", "crowdbench", "run"]
    seeds = "seed=" + ",".join(map(str, SEEDS))
    modes = {
        "basic (sequential)": [*cli, "-m", seeds, *recipe(args.frames)],
        "joblib, 2 workers": [*cli, "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", seeds,
                              *recipe(args.frames)],
        "ray, local cluster of 2 CPUs": [*cli, "-m", "hydra/launcher=ray", "hydra.launcher.ray.init.num_cpus=2",
                                         seeds, *recipe(args.frames)],
    }
    rows = {}
    for name, cmd in modes.items():
        d = args.out / name.split(",")[0].split()[0]
        rows[name] = (timed([*cmd, f"out={d}"], env), successes(d))
    # no engine: one `crowdbench run` per seed, two at a time
    hand = args.out / "by_hand"
    lines = "\n".join(" ".join([*cli, *recipe(args.frames), f"seed={s}", f"out={hand}/{s}"]) for s in SEEDS)
    t = time.perf_counter()
    subprocess.run(["xargs", "-P", "2", "-I{}", "sh", "-c", "{} >/dev/null 2>&1"], input=lines, text=True, env=env,
                   check=True)
    by_hand = time.perf_counter() - t
    hand_success = [json.loads((hand / str(s) / "results.json").read_text())["average_paper_scenes"]["success_rate"]
                    for s in SEEDS]
    print(f"## 3-seed sweep, {args.frames} frames per run (experiment=leaderboard_scratch method=gatedgcn_td3), "
          f"{os.cpu_count()} cores")
    print("| mode | wall time (s) | vs two processes by hand | average success per seed |")
    print("|---|---|---|---|")
    for name, (wall, succ) in rows.items():
        print(f"| {name} | {wall:.1f} | {100 * (wall / by_hand - 1):+.1f}% | {', '.join(f'{s:.3f}' for s in succ)} |")
    print(f"| two processes by hand (xargs -P 2) | {by_hand:.1f} | - | {', '.join(f'{s:.3f}' for s in hand_success)} |")
    started, first, later = ray_startup()
    print(f"\nRay: local cluster start {started:.1f} s; first empty task {first:.2f} s; a later one {later * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
