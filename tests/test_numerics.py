"""Official evaluation runs on one numerical path whatever the caller's CPU settings.

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
