"""What isolating submissions costs: one learned submission's full protocol-v1 evaluation in the
harness process (how the harness evaluated before workers) against a worker process, unconfined
and confined by bubblewrap; the per-episode outcomes must be identical.

    python benchmarks/bench_isolation.py [NAME ...]     (default: mlp_td3_s0 gatedgcn_td3_s0)

Run with nothing else on the machine; the evaluation runs single-threaded, on the pinned numerical
path, as ``crowdbench leaderboard`` does.
"""

from __future__ import annotations

import os
import sys

from crowdbench.numerics import pin

pin()  # before torch: the leaderboard's numerical path

import json
import tempfile
import time
from pathlib import Path

import torch

from crowdbench import policies
from crowdbench.envs.protocol import EVAL_SCENES
from crowdbench.leaderboard.sandbox import Limits, bubblewrap
from crowdbench.leaderboard.submission import read_submission
from crowdbench.leaderboard.tracks import TRACKS, evaluate_track
from crowdbench.leaderboard.worker import WorkerPolicy

ROOT = Path(__file__).resolve().parents[1] / "leaderboard" / "submissions"


def outcomes(policy) -> tuple[float, str]:
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        evaluate_track(TRACKS["v1"], policy, list(EVAL_SCENES), None, Path(tmp), {})
        wall = time.perf_counter() - t
        rows = [json.loads(line) for line in (Path(tmp) / "episodes.jsonl").read_text().splitlines()]
    return wall, "".join(r["outcome"][0] for r in rows)


def main(names: list[str]) -> None:
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, capability {torch.backends.cpu.get_cpu_capability()}, "
          f"{os.cpu_count()} cores; v1: {len(EVAL_SCENES)} scenes x 250 episodes\n")
    print("| submission | in-process (s) | worker, no sandbox (s) | worker, bubblewrap (s) | worker start (s) | outcomes |")
    print("|---|---|---|---|---|---|")
    for name in names:
        sub = read_submission(ROOT / name)
        t = time.perf_counter()
        local = policies.from_checkpoint(sub.checkpoint)
        load_local = time.perf_counter() - t
        base, ref = outcomes(local)
        cells, same, start = [], True, []
        for sandbox in ("none", "bubblewrap"):
            if sandbox == "bubblewrap" and bubblewrap() is None:
                cells.append("n/a (no bwrap)")
                continue
            t = time.perf_counter()
            with WorkerPolicy(sub.dir, name, Limits(sandbox=sandbox)) as p:
                start.append(time.perf_counter() - t)
                wall, got = outcomes(p)
            cells.append(f"{wall + start[-1]:.1f}")
            same &= got == ref
        print(f"| {name} | {base + load_local:.1f} | {' | '.join(cells)} | {max(start):.1f} | "
              f"{'identical' if same else 'DIFFERENT'} |", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:] or ["mlp_td3_s0", "gatedgcn_td3_s0"])
