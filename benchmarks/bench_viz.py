"""Evaluation time with rerun recording off and on, and the size of the recordings.

Usage: python benchmarks/bench_viz.py [--threads 1] [--episodes 250] [--repeats 2] [--scene students003]

The policy is an (untrained) TD3 actor with the ``gatedgcn`` encoder (D = 32), so the
attention path is exercised. ``off`` is ``evaluate(..., recorder_factory=None)`` (the default: no
recorder object, no viz import); ``on-N`` records N of the evaluated episodes. Each mode runs
``--repeats`` times, interleaved; the minimum wall time is reported.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from crowdbench.algos.actors import build_actor
from crowdbench.algos.checkpoint import LearnedPolicy
from crowdbench.cli import compose
from crowdbench.protocols.replay import evaluate


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--episodes", type=int, default=250)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--scene", default="students003")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    policy = LearnedPolicy(build_actor("td3", {"name": "gatedgcn", "dim": 32, "layers": 2, "k": 8}, 1.0),
                           name="td3-gatedgcn-untrained")
    from crowdbench.envs.protocol import load_episodes
    from crowdbench.protocols.engine import select_episodes

    ids = [e["episode"] for e in select_episodes(load_episodes(a.scene), a.episodes)]
    modes = {"off": None, "on-1": ids[:1], "on-5": ids[:5]}
    best: dict[str, float] = {}
    sizes: dict[str, list[int]] = {}
    for _ in range(a.repeats):
        for mode, rec_ids in modes.items():
            with tempfile.TemporaryDirectory() as tmp:
                factory = None
                if rec_ids is not None:
                    from crowdbench.viz.record import make_recorder_factory

                    cfg = compose(["viz.record=true", f"viz.episodes=[{','.join(map(str, rec_ids))}]",
                                   f"eval.episodes={a.episodes}", f"eval.scenes=[{a.scene}]"])
                    factory = make_recorder_factory(policy, cfg, Path(tmp), [a.scene])
                t0 = time.perf_counter()
                evaluate(policy, [a.scene], a.episodes, recorder_factory=factory)
                best[mode] = min(best.get(mode, float("inf")), time.perf_counter() - t0)
                sizes[mode] = [f.stat().st_size for f in Path(tmp).rglob("*.rrd")]
    print(f"{a.scene}, {a.episodes} episodes in one batch, {a.threads} thread(s), best of {a.repeats}")
    for mode, t in best.items():
        s = sizes[mode]
        extra = f", {len(s)} recording(s), {sum(s) / max(len(s), 1) / 1e3:.0f} kB each" if s else ""
        print(f"  {mode:<5} {t:6.2f} s ({(t / best['off'] - 1) * 100:+.1f}% vs off){extra}")


if __name__ == "__main__":
    main()
