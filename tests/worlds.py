"""Test shorthands for protocol-v1 worlds: build one on a scene, reset it from full-batch ``t0``/``angle``."""

from __future__ import annotations

import torch

from crowdbench.envs.factory import replay_world, selfplay_world


def replay_sim(scene, batch: int, cfg=None):
    world, scenario = replay_world(scene, batch, cfg)
    world.scenario = scenario
    return world


def reset_v1(world, mask: torch.Tensor, t0: torch.Tensor, angle: torch.Tensor) -> None:
    """``World.reset`` from ``[B]`` start indices and angles (only the masked entries are used)."""
    world.reset(mask, world.scenario.episodes(t0[mask], angle[mask]))


def selfplay_sim(batch: int, cfg):
    world, scenario = selfplay_world(cfg, batch)
    world.scenario = scenario
    return world


def reset_sp(world, mask: torch.Tensor, start: torch.Tensor, goal: torch.Tensor, t0: torch.Tensor | None = None):
    """``World.reset`` from ``[B, A, 2]`` starts and goals (only the masked entries are used)."""
    t0 = torch.zeros(world.B, dtype=torch.long) if t0 is None else t0
    world.reset(mask, {"start": start[mask], "goal": goal[mask], "t0": t0[mask]})


def students_obs(batch: int, steps: int) -> dict:
    """Real STUDENTS001 observations ``steps`` steps into ``batch`` episodes spread over the scene
    (the robot walking at 1 m/s along x): many humans, some robots isolated."""
    import math

    from crowdbench.data.scenes import load_scene

    sim = replay_sim(load_scene("students001"), batch)
    t0 = torch.linspace(0, sim.scenario.last_start, batch).long()
    ang = torch.linspace(0, 2 * math.pi, batch + 1)[:-1]
    reset_v1(sim, torch.ones(batch, dtype=torch.bool), t0, ang)
    for _ in range(steps):
        sim.step(torch.tensor([1.0, 0.0]).expand(batch, 1, 2))
    return sim.observe()


# every encoder at a test's size (D = 16)
SMALL_ENCODERS = {"gatedgcn": {"dim": 16}, "gcn": {"dim": 16}, "mlp": {"dim": 16, "hidden": [32]},
                  "sarl": {"dim": 16, "embed": [16, 16], "interact": [16], "attention": [16], "hidden": [16]},
                  "lstm_rl": {"dim": 16, "hidden_size": 16, "hidden": [16]}, "rgl": {"dim": 16, "embed": [16]},
                  "gat": {"dim": 16}, "dsrnn": {"dim": 16, "embed": 16, "attn_dim": 8}}


def outputs_under_two_targets(tmp_path, script: str, args: list[str], timeout: float) -> dict:
    """``{target: array}``: ``script`` (writes its array to ``argv[1]``, prints numba's CPU name) run for a
    generic x86-64 (SSE2 only) and for this CPU, in two processes, each with its own empty numba cache (a
    cache of another target is never loaded: numba keys it by CPU name and features)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    import numpy as np

    root = Path(__file__).resolve().parents[1]
    got = {}
    for target in ("generic", "host"):
        env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / f"cache-{target}"), "PYTHONPATH": str(root)}
        env.pop("NUMBA_CPU_NAME", None)
        env.pop("NUMBA_CPU_FEATURES", None)
        if target == "generic":
            env["NUMBA_CPU_NAME"] = "generic"
        out = tmp_path / f"{target}.npy"
        p = subprocess.run([sys.executable, "-c", script, str(out), *args], env=env, capture_output=True, text=True,
                           timeout=timeout, check=False, cwd=tmp_path)
        assert p.returncode == 0, p.stderr[-2000:]
        assert p.stdout == target
        got[target] = np.load(out)
    return got
