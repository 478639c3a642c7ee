"""The package works installed as a wheel (not editable), run from a directory outside the repository."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_installed_wheel_evaluates_from_outside_the_repository(tmp_path):
    # the wheel is built from the checkout with the installed setuptools (no network), then installed
    # without its dependencies into a venv that sees the packages of the interpreter running pytest (torch
    # etc.) through a .pth line. Not `--system-site-packages`: a venv made from a venv's interpreter sees
    # the base interpreter's packages, which on a fresh machine hold no torch.
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                    str(tmp_path / "whl"), str(ROOT)], check=True, timeout=300)
    (wheel,) = (tmp_path / "whl").glob("crowdbench-*.whl")
    subprocess.run([sys.executable, "-m", "venv", str(tmp_path / "venv")], check=True)
    bin_dir = tmp_path / "venv" / "bin"
    (venv_site,) = (tmp_path / "venv" / "lib").glob("python3*/site-packages")
    deps = [p for p in sys.path if p.endswith(("site-packages", "dist-packages"))]
    (venv_site / "dependencies.pth").write_text("\n".join(deps) + "\n")
    subprocess.run([bin_dir / "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True, timeout=300)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    where = subprocess.run([bin_dir / "python", "-c", "import crowdbench; print(crowdbench.__file__)"], cwd=elsewhere,
                           env=env, capture_output=True, text=True, check=True).stdout.strip()
    assert where.startswith(str(tmp_path / "venv")), where  # the wheel's copy, not the checkout
    p = subprocess.run([bin_dir / "crowdbench", "eval", "policy=orca", "eval.episodes=10", "eval.scenes=[hotel]",
                        "out=o"], cwd=elsewhere, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads((elsewhere / "o" / "results.json").read_text())
    assert list(res["scenes"]) == ["hotel"] and res["numerics"]["cpu_capability"] == "DEFAULT"
    assert 0.0 <= res["scenes"]["hotel"]["success_rate"]["mean"] <= 1.0
    # the compiled ORCA from the wheel: equal to the torch solver; a second process loads it from numba's cache
    orca = ("import time; t = time.perf_counter(); import torch; from crowdbench.envs.humans import orca, orca_kernel; "
            "from crowdbench.envs.humans.rvo2_reference import random_configs; c = random_configs('dense', 50, 8, 1); "
            "p = dict(time_horizon=5.0, dt=0.25, neighbor_dist=10.0, max_neighbors=10); "
            "assert orca_kernel.__file__.startswith({!r}); "
            "assert torch.equal(orca_kernel.orca_velocities(**c, **p), orca.orca_velocities(**c, **p)); "
            "print(time.perf_counter() - t)").format(str(tmp_path / "venv"))
    for _ in range(2):
        k = subprocess.run([bin_dir / "python", "-c", orca], cwd=elsewhere, env=env, capture_output=True, text=True,
                           timeout=300, check=False)
        assert k.returncode == 0, k.stderr[-2000:]
    assert list((venv_site / "crowdbench" / "envs" / "humans" / "__pycache__").glob("orca_kernel*.nbi"))
    lb = subprocess.run([bin_dir / "crowdbench", "leaderboard", "--check"], cwd=elsewhere, env=env,
                        capture_output=True, text=True, timeout=300, check=False)
    assert lb.returncode == 1 and "no submissions under leaderboard/submissions" in lb.stdout + lb.stderr
