"""The Python API (crowdbench/api.py): docs/api.md's examples run as written; numerics are checked; envs by name."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_api_docs_examples_run():
    """In a fresh interpreter from the repository root: ``import crowdbench.api`` first pins the numerics."""
    env = {k: v for k, v in os.environ.items() if k not in ("ATEN_CPU_CAPABILITY", "MKL_CBWR", "NPY_DISABLE_CPU_FEATURES")}
    p = subprocess.run([sys.executable, "-m", "doctest", "-o", "ELLIPSIS", "-o", "NORMALIZE_WHITESPACE",
                        "docs/api.md"], cwd=ROOT, env={**env, "OMP_NUM_THREADS": "1"}, capture_output=True,
                       text=True, timeout=600, check=False)
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]


def test_evaluate_refuses_official_numbers_off_the_pinned_path():
    import torch

    from crowdbench import api

    torch.ones(2).sum()  # this process dispatched kernels before any pin: the machine's own
    if os.environ.get("ATEN_CPU_CAPABILITY") == "default" and torch.backends.cpu.get_cpu_capability() == "DEFAULT":
        pytest.skip("this process runs on the pinned path already")
    with pytest.raises(api.NumericsError, match="import crowdbench.api before torch"):
        api.evaluate(api.policy("straight"), "v1", scenes=["hotel"], episodes=1)
    res = api.evaluate(api.policy("straight"), "v1", scenes=["hotel"], episodes=1, pinned=False)
    assert res["scenes"]["hotel"]["success_rate"]["n"] == 1


def test_bad_names_are_one_line_errors():
    from crowdbench import api

    with pytest.raises(ValueError, match="unknown protocol 'v3'; valid: v1, v2-orca"):
        api.evaluate(api.policy("straight"), "v3", pinned=False)
    with pytest.raises(ValueError, match="scenes apply to the replay protocols"):
        api.evaluate(api.policy("straight"), "crowdnav-circle5", scenes=["hotel"], pinned=False)
    with pytest.raises(ValueError, match="unknown env 'crowd'; valid: replay, reactive_replay, crowdnav, selfplay"):
        api.make_env("crowd")
    with pytest.raises(ValueError, match="unknown api 'gym'"):
        api.make_env("replay", api="gym")
    with pytest.raises(ValueError, match="one robot"):
        api.make_env("selfplay", api="gymnasium")


@pytest.mark.filterwarnings("ignore:.*observation space (minimum|maximum) value is:UserWarning")  # positions: unbounded
def test_gymnasium_ids_and_the_env_checker():
    import gymnasium
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make("crowdbench.envs.registry:crowdbench/Replay-v0", scene="students003")
    check_env(env.unwrapped, skip_render_check=True)
    obs, _ = env.reset(seed=3)
    again, _ = env.reset(seed=3)
    assert all((obs[k] == again[k]).all() for k in obs)  # seeded
    steps, done = 0, False
    while not done:  # straight to the goal until the episode ends (at the latest at the time limit)
        goal = obs["robot"][4:6]
        obs, _, terminated, truncated, info = env.step(goal / max(1e-6, float((goal ** 2).sum() ** 0.5)))
        steps, done = steps + 1, terminated or truncated
    assert info["outcome"] in ("success", "collision", "timeout") and steps <= 100
