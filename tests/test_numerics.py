"""Official evaluation runs on one numerical path whatever the caller's CPU settings.

What has to be pinned (docs/benchmarks.md, "The pinned evaluation path"): ATen's vectorised kernels
compute exactly-rounded ops (add, mul, relu, sums over a row, min, copies) with the same bits as the
portable ones, but not ``sigmoid``, ``softmax``, ``atan2`` or ``vector_norm`` (SLEEF approximations, other
reduction orders); MKL's native sgemm differs from its COMPATIBLE branch, and the committed numbers are
COMPATIBLE's. ATen's capability is one switch for all its kernels, so the ATen pin stays whole.

gatedgcn_ddpg_s1 on eth is a shipped checkpoint whose episodes depend on the kernels when nothing is
pinned: on an AVX-512 machine, ATen's avx512 kernels or MKL's native code path turn one of its 250
episodes into a success (benchmarks/bench_numerics.py). The ``crowdbench`` entry point pins the path
(crowdbench/numerics.py), so the three settings below must give the same episodes.jsonl.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from crowdbench.numerics import PINNED

# ops of the evaluation path (graph encoders, attention, the world's geometry) on fixed inputs built by
# exact integer arithmetic; prints the capability torch runs and a digest of every op's output bytes
PROBE = """
import hashlib, json
import numpy as np
import torch
torch.set_num_threads(1)
i = np.arange(4096 * 64, dtype=np.uint64)
u = ((i * np.uint64(2654435761)) % np.uint64(2 ** 32)).astype(np.float64) / 2 ** 32
x = torch.from_numpy((u * 8 - 4).astype(np.float32)).view(4096, 64)
y = x.flip(0).contiguous()
w = (x[:64] / 8).contiguous()
ops = {"add": x + y, "mul": x * y, "relu": torch.relu(x), "sum": x.sum(-1), "amin": x.amin(-1),
       "sigmoid": torch.sigmoid(x), "softmax": torch.softmax(x, -1), "atan2": torch.atan2(x, y),
       "vector_norm": torch.linalg.vector_norm(x.view(-1, 2), dim=-1), "mm": x @ w}
print(json.dumps({"cap": torch.backends.cpu.get_cpu_capability(),
                  "digest": {k: hashlib.sha256(v.contiguous().numpy().tobytes()).hexdigest()[:16]
                             for k, v in ops.items()}}))
"""
# the pinned path's bits, computed on an AVX-512 AMD EPYC (torch 2.15.0, MKL 2024.2): the same on every x86 CPU
PINNED_DIGEST = {"add": "f4a1fb7468a78a42", "mul": "9de8704412ad36a0", "relu": "844051c857a7e914",
                 "sum": "483c2ecda174bd87", "amin": "56fe83f197afb3d4", "sigmoid": "fd791bdf9148b679",
                 "softmax": "b161861d7bb3846c", "atan2": "543c66fc75f09c8f", "vector_norm": "b7970fb1fae00806",
                 "mm": "0dd89a3e87dee6ec"}
EXACT = {"add", "mul", "relu", "sum", "amin"}  # the same bits from every ATen kernel and MKL branch


def _probe(**env) -> dict:
    p = subprocess.run([sys.executable, "-c", PROBE], env={**os.environ, "OMP_NUM_THREADS": "1", **env},
                       capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


def test_the_pinned_path_computes_the_committed_bits():
    r = _probe(**PINNED)
    assert r["cap"] == "DEFAULT"
    assert r["digest"] == PINNED_DIGEST


@pytest.mark.slow
def test_each_pinned_component_is_needed():
    # ATen's AVX2 kernels (MKL pinned): the exactly-rounded ops agree with the portable ones, the
    # approximated ones do not, so ATen's kernels must be pinned
    aten = _probe(**{**PINNED, "ATEN_CPU_CAPABILITY": "avx2"})
    if aten["cap"] != "AVX2":
        pytest.skip("this CPU has no AVX2")
    assert {k for k, v in aten["digest"].items() if v != PINNED_DIGEST[k]} == {"sigmoid", "softmax", "atan2",
                                                                              "vector_norm"}
    # MKL's AVX2 branch (ATen pinned): only the matrix product differs, so MKL's branch must be pinned
    mkl = _probe(**{**PINNED, "MKL_CBWR": "AVX2"})
    assert {k for k, v in mkl["digest"].items() if v != PINNED_DIGEST[k]} == {"mm"}
    assert all(aten["digest"][k] == mkl["digest"][k] == PINNED_DIGEST[k] for k in EXACT)

ROOT = Path(__file__).resolve().parents[1]
CKPT = ROOT / "leaderboard" / "submissions" / "gatedgcn_ddpg_s1" / "checkpoint.pt"


@pytest.mark.slow
def test_episodes_are_the_same_under_every_cpu_capability(tmp_path):
    episodes = {}
    for cap in ("default", "avx2", "avx512"):
        env = {**os.environ, "ATEN_CPU_CAPABILITY": cap, "MKL_CBWR": "AUTO", "OMP_NUM_THREADS": "1"}
        out = tmp_path / cap
        p = subprocess.run([sys.executable, "-m", "crowdbench", "eval", f"policy={CKPT}", "eval.scenes=[eth]",
                            "eval.save_episodes=true", f"out={out}"], env=env, capture_output=True, text=True,
                           timeout=600, check=False)
        assert p.returncode == 0, p.stderr[-2000:]
        assert json.loads((out / "results.json").read_text())["numerics"]["cpu_capability"] == "DEFAULT"
        episodes[cap] = (out / "episodes.jsonl").read_text()
    assert episodes["avx2"] == episodes["default"] and episodes["avx512"] == episodes["default"]
    committed = json.loads((ROOT / "leaderboard" / "results" / "gatedgcn_ddpg_s1" / "results.json").read_text())
    outcomes = "".join({"success": "S", "collision": "C", "timeout": "T"}[json.loads(line)["outcome"]]
                       for line in episodes["default"].splitlines())
    assert outcomes == committed["episode_outcomes"]["eth"]  # the leaderboard's numbers are this path's


def test_numpy_is_pinned_before_it_is_imported():
    # numpy reads NPY_DISABLE_CPU_FEATURES once, at import: the entry point must pin before anything imports it
    code = "import sys, crowdbench.entry; print('numpy' in sys.modules)"
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert p.stdout.strip() == "False"
    # every name is one the installed numpy dispatches (an unknown one only warns, and pins nothing),
    # and its float64 cos (CrowdNav's circle placement) then runs no AVX-512 kernel on any machine
    code = ("import json; from numpy.lib.introspect import opt_func_info; "
            "print(json.dumps(opt_func_info(func_name='^cos$', signature='d')['cos']['dd']))")
    p = subprocess.run([sys.executable, "-W", "error::ImportWarning", "-c", code], env={**os.environ, **PINNED},
                       capture_output=True, text=True, timeout=120, check=False)
    assert p.returncode == 0, p.stderr[-2000:]
    current = json.loads(p.stdout)["current"]
    assert "X86_V4" not in current and "AVX512" not in current
