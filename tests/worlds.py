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
