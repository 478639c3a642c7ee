"""The compiled ORCA solver (crowdbench.envs.humans.orca_kernel) against the torch solver (the reference,
value for value), against RVO2 (pyrvo), and under two CPU targets (the same bytes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from crowdbench.envs.humans import orca, orca_kernel
from crowdbench.envs.humans.rvo2_reference import KINDS, random_configs, rvo2_velocities
from tests.worlds import outputs_under_two_targets

ROOT = Path(__file__).resolve().parents[1]
SMALL = {"time_horizon": 2.0, "dt": 0.25, "neighbor_dist": 4.0, "max_neighbors": 6}
CROWDNAV = {"time_horizon": 5.0, "dt": 0.25, "neighbor_dist": 10.0, "max_neighbors": 10}


def _both(cfg, params):
    return orca_kernel.orca_velocities(**cfg, **params), orca.orca_velocities(**cfg, **params)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("params", [SMALL, CROWDNAV], ids=["small", "crowdnav"])
def test_equals_the_torch_solver(kind, params):
    # 1000 worlds of up to 12 agents per kind (padded at random): every agent's velocity equal
    cfg = random_configs(kind, 1000, 12, seed=100 + KINDS.index(kind))
    ours, ref = _both(cfg, params)
    assert ours.dtype == ref.dtype == torch.float64
    bad = (ours != ref).any(-1)
    assert not bad.any(), f"{int(bad.sum())} of {bad.numel()} agents differ, max {(ours - ref).abs().max():.3g}"


@pytest.mark.parametrize("k", [1, 2, 21, 51])
def test_equals_the_torch_solver_float32_and_crowd_sizes(k):
    # float32 in, float32 out (the world's dtype: returned as computed, invalid agents keep vel); one agent
    # alone (no neighbour slot), more agents than max_neighbors
    cfg = {key: v.float() if v.is_floating_point() else v for key, v in random_configs("dense", 200, max(k, 2),
                                                                                      seed=k).items()}
    if k == 1:
        cfg = {key: v[:, :1] for key, v in cfg.items()}
    ours, ref = _both(cfg, CROWDNAV)
    assert ours.dtype == torch.float32 and torch.equal(ours, ref)
    assert torch.equal(ours[~cfg["valid"]], cfg["vel"][~cfg["valid"]])


def test_padding_anywhere_and_scalar_parameters():
    cfg = random_configs("overlap", 300, 8, seed=5)
    k = cfg["pos"].shape[1]
    g = torch.Generator().manual_seed(0)
    perm = torch.randperm(2 * k, generator=g)  # the valid agents interleaved with garbage ones
    pad = {key: torch.cat([v, torch.randn(v.shape, generator=g, dtype=v.dtype)], 1)[:, perm]
           for key, v in cfg.items() if key != "valid"}
    pad["valid"] = torch.cat([cfg["valid"], torch.zeros_like(cfg["valid"])], 1)[:, perm]
    pad["radius"], pad["max_speed"] = 0.3, 1.2
    ours, ref = _both(pad, SMALL)
    assert torch.equal(ours, ref)
    # ties in distance (agents on a lattice) go by index in both
    lattice = torch.stack(torch.meshgrid(torch.arange(4.0), torch.arange(4.0), indexing="ij"), -1).reshape(1, 16, 2)
    same = {"pos": lattice, "vel": torch.zeros(1, 16, 2), "pref": torch.ones(1, 16, 2) * 0.5,
            "valid": torch.ones(1, 16, dtype=torch.bool), "radius": 0.3, "max_speed": 1.0}
    ours, ref = _both(same, {**SMALL, "max_neighbors": 3})
    assert torch.equal(ours, ref)


def test_agrees_with_rvo2():
    # >= 99.9 % of agents within 1e-3 m/s of RVO2 over 4 kinds x 300 worlds (the torch solver's figure: all of
    # 37531 in benchmarks/bench_orca_model.py); the rest are degenerate linearProgram3 optima (test_orca_model)
    close, total = 0, 0
    for i, kind in enumerate(KINDS):
        cfg = random_configs(kind, 300, 10, seed=200 + i)
        ours = orca_kernel.orca_velocities(**cfg, **SMALL)
        ref = torch.from_numpy(rvo2_velocities(**cfg, **SMALL))
        valid = cfg["valid"]
        diff = (ours - ref).abs().amax(-1)[valid]
        close, total = close + int((diff <= 1e-3).sum()), total + diff.numel()
    assert close / total >= 0.999, f"{close} of {total} within 1e-3 m/s"


def test_the_crowd_moves_the_same_with_either_backend():
    # a CrowdNav world of 20 humans seeing the robot, 40 steps: positions equal step by step
    from crowdbench.envs.crowdnav import CrowdNavConfig
    from crowdbench.envs.factory import crowdnav_world

    traj = {}
    for backend in ("numba", "torch"):
        cfg = CrowdNavConfig(n_humans=20, robot_visible=True, orca_backend=backend)
        world, scen = crowdnav_world(cfg, 16)
        assert world.crowd.params.backend == backend
        eps = scen.cases(range(16), "test")
        world.reset(torch.ones(16, dtype=torch.bool), eps)
        g = torch.Generator().manual_seed(1)
        steps = []
        for _ in range(40):
            world.step(torch.rand(16, 1, 2, generator=g) - 0.5)
            steps.append(world.crowd.pos.clone())
        traj[backend] = torch.stack(steps)
    assert torch.equal(traj["numba"], traj["torch"])


FMA = ("vfmadd", "vfmsub", "vfnmadd", "vfnmsub")


def test_the_fma_check_finds_fma():
    """Control for the check of the slow test below: where the CPU has FMA, a fastmath function's code has
    it (and the same product-plus-sum without fastmath has none)."""
    import numba
    from llvmlite import binding

    if not binding.get_host_cpu_features().get("fma", False):
        pytest.skip("this CPU has no FMA")

    def axpy(a, b, c):
        return a * b + c

    asm = {fm: "\n".join(f.inspect_asm().values()) for fm in (True, False)
           if (f := numba.njit(fastmath=fm)(axpy)) and f(1.0, 2.0, 3.0)}
    assert any(op in asm[True] for op in FMA) and not any(op in asm[False] for op in FMA)


_RUN = r"""
import sys, numpy as np, torch
from crowdbench.envs.humans import orca_kernel
from crowdbench.envs.humans.rvo2_reference import KINDS, random_configs
out = [orca_kernel.orca_velocities(**random_configs(kind, 400, 12, seed=i), time_horizon=5.0, dt=0.25,
       neighbor_dist=10.0, max_neighbors=10).float().numpy() for i, kind in enumerate(KINDS)]
import numba
asm = "".join(f.inspect_asm(sig) for f in (orca_kernel._kernel, orca_kernel._lp1, orca_kernel._lp3,
                 orca_kernel._line, orca_kernel._lp2) for sig in f.signatures)
assert "vmulss" in asm or "mulss" in asm  # compiled here, not loaded from a cache (no code to inspect)
fma = any(op in asm for op in ("vfmadd", "vfmsub", "vfnmadd", "vfnmsub"))
sys.stdout.write((numba.config.CPU_NAME or "host") + (" FMA" if fma else ""))
np.save(sys.argv[1], np.stack(out))
"""


@pytest.mark.slow
def test_the_same_bytes_under_generic_and_host_targets(tmp_path):
    """Compiled for a generic x86-64 (SSE2 only) and for this CPU (AVX2/FMA/...) in two processes, each with
    its own (empty) cache: no FMA instruction in either's code, and the outputs are the same bytes."""
    got = outputs_under_two_targets(tmp_path, _RUN, [], timeout=600)
    assert got["generic"].tobytes() == got["host"].tobytes()
    assert np.isfinite(got["host"]).all()
