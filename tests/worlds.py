"""Test shorthands for protocol-v1 worlds: build one on a scene, reset it from full-batch ``t0``/``angle``."""

from __future__ import annotations

import torch

from crowdbench.envs.factory import replay_world


def replay_sim(scene, batch: int, cfg=None):
    world, scenario = replay_world(scene, batch, cfg)
    world.scenario = scenario
    return world


def reset_v1(world, mask: torch.Tensor, t0: torch.Tensor, angle: torch.Tensor) -> None:
    """``World.reset`` from ``[B]`` start indices and angles (only the masked entries are used)."""
    world.reset(mask, world.scenario.episodes(t0[mask], angle[mask]))
