"""What the pinned numerical path costs, and what it changes: the full protocol (7 scenes x 250
episodes) of ORCA and of one shipped learned checkpoint, each in a fresh interpreter under every
combination of ATen's CPU capability and MKL's reproducibility mode (crowdbench/numerics.py).

    python benchmarks/bench_numerics.py [--checkpoint leaderboard/submissions/gatedgcn_ddpg_s1/checkpoint.pt]

Prints the wall time of the evaluation (without start-up) and the episode outcomes that differ from the
pinned path's. Run it with nothing else running on the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

CHILD = """
import json, sys, time
from crowdbench.eval import evaluate
from crowdbench.envs.protocol import EVAL_SCENES
from crowdbench import policies
from crowdbench.cli import compose
name = sys.argv[1]
policy = policies.build(name, compose([])) if name == "orca" else None
if policy is None:
    from crowdbench.algos.checkpoint import policy_from_checkpoint
    policy = policy_from_checkpoint(name)
t = time.perf_counter()
r = evaluate(policy, list(EVAL_SCENES), None, save_episodes=False)
wall = time.perf_counter() - t
print(json.dumps({"wall": wall, "numerics": r["numerics"],
                  "outcomes": {s: r["scenes"][s]["success_rate"]["mean"] for s in r["scenes"]}}))
"""


def run(policy: str, aten: str, mkl: str) -> dict:
    env = {**os.environ, "ATEN_CPU_CAPABILITY": aten, "MKL_CBWR": mkl, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", CHILD, policy], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default="leaderboard/submissions/gatedgcn_ddpg_s1/checkpoint.pt")
    a = ap.parse_args()
    print("| policy | ATen kernels | MKL_CBWR | evaluation (s) | success rates that differ from the pinned path |")
    print("|---|---|---|---|---|")
    for policy in ("orca", a.checkpoint):
        pinned = run(policy, "default", "COMPATIBLE")
        for aten, mkl in (("default", "COMPATIBLE"), ("avx2", "AUTO"), ("avx512", "AUTO"), ("default", "AUTO"),
                          ("avx512", "COMPATIBLE")):
            r = pinned if (aten, mkl) == ("default", "COMPATIBLE") else run(policy, aten, mkl)
            diff = [f"{s} {pinned['outcomes'][s]:.3f} -> {v:.3f}" for s, v in r["outcomes"].items()
                    if v != pinned["outcomes"][s]]
            label = "ORCA" if policy == "orca" else os.path.basename(os.path.dirname(policy))
            print(f"| {label} | {r['numerics']['cpu_capability']} | {mkl} | {r['wall']:.1f} | "
                  f"{'; '.join(diff) or 'none'} |")


if __name__ == "__main__":
    main()
