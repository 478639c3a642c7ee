"""What the pinned numerical path costs, where the cost is, and what each of its components changes
(crowdbench/numerics.py).

    python benchmarks/bench_numerics.py [--submissions gatedgcn_td3_s0,mlp_td3_s0] [--scenes all] [--ops]

``eval``: each shipped submission's protocol-v1 evaluation (the harness's ``evaluate_track``, one thread,
in a fresh interpreter) under nothing pinned, each component pinned alone, everything pinned, and the
pin with one component swapped for another CPU's (ATen's AVX2 / AVX-512 kernels, MKL's AVX2 / AVX-512
branch). Prints the CPU time of the evaluation (``time.process_time``, without start-up: steadier than
wall time on a shared machine), the load average, and whether the episode outcomes and the summary
equal the committed ``leaderboard/results``.

``--ops``: CPU time per call of the evaluation path's hot ops (``[8192, 64]`` float32, one thread) under
ATen's default / AVX2 / AVX-512 kernels and MKL's COMPATIBLE / AVX2 branch, and whether each op's bits
differ from the pinned path's.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from crowdbench.numerics import PINNED

ROOT = Path(__file__).resolve().parents[1]

EVAL_CHILD = """
import hashlib, json, sys, tempfile, time
from pathlib import Path
import torch
torch.set_num_threads(1)
from crowdbench.algos.checkpoint import policy_from_checkpoint
from crowdbench.envs.protocol import EVAL_SCENES
from crowdbench.leaderboard.tracks import TRACKS, evaluate_track
root, name, scenes = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
scenes = list(EVAL_SCENES) if scenes == "all" else scenes.split(",")
policy = policy_from_checkpoint(root / "leaderboard" / "submissions" / name / "checkpoint.pt")
t = time.process_time()
with tempfile.TemporaryDirectory() as d:
    r = evaluate_track(TRACKS["v1"], policy, scenes, None, Path(d), {})
    rows = [json.loads(line) for line in (Path(d) / "episodes.jsonl").read_text().splitlines()]
cpu = time.process_time() - t
outcomes = {s: "" for s in scenes}
for row in rows:
    outcomes[row["scene"]] += {"success": "S", "collision": "C", "timeout": "T"}[row["outcome"]]
committed = json.loads((root / "leaderboard" / "results" / name / "results.json").read_text())
print(json.dumps({"cpu": cpu, "cap": r["numerics"]["cpu_capability"],
                  "outcomes": all(outcomes[s] == committed["episode_outcomes"][s] for s in scenes),
                  "summary": all(json.dumps(r["scenes"][s], sort_keys=True)
                                 == json.dumps(committed["scenes"][s], sort_keys=True) for s in scenes)}))
"""

OPS_CHILD = """
import json, sys, time
import numpy as np
import torch
torch.set_num_threads(1)
rng = np.random.default_rng(0)
R = lambda *shape: torch.from_numpy(rng.standard_normal(shape).astype(np.float32))
x, y, b, w, s = R(8192, 64) * 3, R(8192, 64), R(64), R(64, 64) / 8, R(8192, 8)
OPS = {"add": lambda: x + y, "add (bias)": lambda: x + b, "mul": lambda: x * y, "sub": lambda: x - y,
       "div": lambda: x / (y.abs() + 1), "relu": lambda: torch.relu(x), "where": lambda: torch.where(x > 0, x, y),
       "exp": lambda: torch.exp(x), "tanh": lambda: torch.tanh(x), "sigmoid": lambda: torch.sigmoid(x),
       "softmax": lambda: torch.softmax(s, -1), "atan2": lambda: torch.atan2(x, y),
       "vector_norm": lambda: torch.linalg.vector_norm(x[:, :2], dim=-1), "sum": lambda: x.sum(-1),
       "amin": lambda: x.amin(-1), "topk": lambda: torch.topk(s, 4, -1).values, "cat": lambda: torch.cat([x, y], -1),
       "mm": lambda: x @ w, "linear": lambda: torch.nn.functional.linear(x, w, b)}
out, us = {}, {}
for k, f in OPS.items():
    out[k] = f()
    t = time.process_time()
    for _ in range(30):
        f()
    us[k] = (time.process_time() - t) / 30 * 1e6
torch.save(out, sys.argv[1])
print(json.dumps({"cap": torch.backends.cpu.get_cpu_capability(), "us": us}))
"""


def child(code: str, args: list[str], setting: dict) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in PINNED}
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", RL_WARNINGS="0", **setting)
    p = subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, check=True,
                       cwd=ROOT)
    return json.loads(p.stdout.strip().splitlines()[-1])


def settings() -> dict[str, dict]:
    npy = {"NPY_DISABLE_CPU_FEATURES": PINNED["NPY_DISABLE_CPU_FEATURES"]}
    return {"none": {}, "ATen only": {"ATEN_CPU_CAPABILITY": "default"}, "MKL only": {"MKL_CBWR": "COMPATIBLE"},
            "NumPy only": npy, "all (the pin)": dict(PINNED),
            "pin, ATen avx2": {**PINNED, "ATEN_CPU_CAPABILITY": "avx2"},
            "pin, ATen avx512": {**PINNED, "ATEN_CPU_CAPABILITY": "avx512"},
            "pin, MKL AVX2": {**PINNED, "MKL_CBWR": "AVX2"}, "pin, MKL AVX512": {**PINNED, "MKL_CBWR": "AVX512"}}


def bench_eval(submissions: list[str], scenes: str) -> None:
    print("| submission | pinned | ATen | CPU s | load | outcomes = committed | summary = committed |")
    print("|---|---|---|---|---|---|---|")
    for name in submissions:
        for label, setting in settings().items():
            load = os.getloadavg()[0]
            r = child(EVAL_CHILD, [str(ROOT), name, scenes], setting)
            print(f"| {name} | {label} | {r['cap']} | {r['cpu']:.2f} | {load:.1f} | {r['outcomes']} | {r['summary']} |",
                  flush=True)


def bench_ops(tmp: Path) -> None:
    import torch

    cfgs = {"pinned": dict(PINNED), "ATen avx2": {**PINNED, "ATEN_CPU_CAPABILITY": "avx2"},
            "ATen avx512": {**PINNED, "ATEN_CPU_CAPABILITY": "avx512"}, "MKL AVX2": {**PINNED, "MKL_CBWR": "AVX2"},
            "native": {"ATEN_CPU_CAPABILITY": "avx512", "MKL_CBWR": "AUTO"}}
    res, outs = {}, {}
    for label, setting in cfgs.items():
        res[label] = child(OPS_CHILD, [str(tmp / f"{len(res)}.pt")], setting)
        outs[label] = torch.load(tmp / f"{len(res) - 1}.pt")
    print(f"load {os.getloadavg()[0]:.1f}; CPU us per call, * = bits differ from the pinned path's")
    print("| op | " + " | ".join(f"{k} ({res[k]['cap']})" for k in cfgs) + " |")
    print("|---|" + "---|" * len(cfgs))
    for op in res["pinned"]["us"]:
        cells = [f"{res[k]['us'][op]:.0f}{'' if torch.equal(outs[k][op], outs['pinned'][op]) else ' *'}" for k in cfgs]
        print(f"| {op} | " + " | ".join(cells) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--submissions", default="gatedgcn_td3_s0,mlp_td3_s0")
    ap.add_argument("--scenes", default="all", help="comma-separated protocol-v1 scenes, or all")
    ap.add_argument("--ops", action="store_true", help="the op microbenchmark instead of the evaluations")
    a = ap.parse_args()
    if a.ops:
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            bench_ops(Path(d))
    else:
        bench_eval(a.submissions.split(","), a.scenes)


if __name__ == "__main__":
    main()
