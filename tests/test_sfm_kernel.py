"""The compiled social force (crowdbench.envs.humans.sfm_kernel) against the torch model (the reference),
hand values, its exp/atan2 against Python's math, and under two CPU targets (the same bytes)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from crowdbench.envs.humans import sfm, sfm_kernel
from crowdbench.envs.humans.sfm import SFMParams
from tests.worlds import outputs_under_two_targets

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("sparse", "dense", "overlap", "at_goal")
# max deviation from torch, in units of the dtype's eps (m/s, velocities of ~1 m/s): measured 4 in float32
# and in float64 over the worlds below; the bound leaves room for other inputs
BOUND = 16


def random_worlds(kind: str, n: int, m: int, r: int, seed: int, dtype=torch.float32):
    """``n`` worlds of up to ``m`` humans (padded at random, garbage in the padding) and ``r`` bodies."""
    g = torch.Generator().manual_seed(seed)
    size = {"sparse": 20.0, "dense": 4.0, "overlap": 1.5, "at_goal": 6.0}[kind]
    pos = (torch.rand(n, m, 2, generator=g) - 0.5) * size
    if kind == "overlap":  # some humans exactly on others
        pos[:, 1::3] = pos[:, ::3][:, : pos[:, 1::3].shape[1]]
    goal = pos + torch.randn(n, m, 2, generator=g) * (0.1 if kind == "at_goal" else 5.0)
    vel = torch.randn(n, m, 2, generator=g) * 0.8
    valid = torch.rand(n, m, generator=g) > 0.2
    garbage = torch.where(torch.rand(n, m, 1, generator=g) < 0.5, float("nan"), 1e6)
    pos, vel = torch.where(valid[..., None], pos, garbage), torch.where(valid[..., None], vel, garbage)
    v_pref = 0.5 + torch.rand(n, m, generator=g)
    others = {"others_pos": (torch.rand(n, r, 2, generator=g) - 0.5) * size,
              "others_vel": torch.randn(n, r, 2, generator=g), "others_valid": torch.rand(n, r, generator=g) > 0.3,
              "others_radius": 0.2 + 0.2 * torch.rand(n, r, generator=g)} if r else {}
    cast = lambda t: t.to(dtype) if t.is_floating_point() else t
    return (cast(pos), cast(vel), cast(goal), valid, 0.3, cast(v_pref)), {k: cast(v) for k, v in others.items()}


def deviation(dtype, kind, r, params, seed):
    args, others = random_worlds(kind, 500, 10, r, seed, dtype)
    ours = sfm_kernel.social_force_velocities(*args, dt=0.25, params=params, **others)
    ref = sfm.social_force_velocities(*args, dt=0.25, params=params, **others)
    assert ours.dtype == ref.dtype == dtype and torch.isfinite(ref).all() and torch.isfinite(ours).all()
    assert torch.equal(ours[~args[3]], ref[~args[3]])  # absent humans: zeros in both
    return float((ours - ref).abs().max() / torch.finfo(dtype).eps), float((ours == ref).all(-1).float().mean())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("kind", KINDS)
def test_agrees_with_the_torch_model(kind, dtype):
    # 500 worlds of up to 10 humans per case: no bodies, 2 bodies (robots) with the body force, and without it
    for i, (r, params) in enumerate([(0, SFMParams()), (2, SFMParams()), (2, SFMParams(body_strength=0.0))]):
        dev, same = deviation(dtype, kind, r, params, seed=10 * KINDS.index(kind) + i)
        assert dev <= BOUND, f"{kind} r={r}: {dev:.1f} eps from torch ({same:.0%} of the velocities equal)"


def test_standing_humans_on_a_lattice():
    # equal coordinates and zero velocities: the pairs the kernel computes both ways (a zero difference keeps
    # its sign); against torch in float64 and float32
    lat = torch.stack(torch.meshgrid(torch.arange(4.0), torch.arange(4.0), indexing="ij"), -1).reshape(1, 16, 2)
    for dtype in (torch.float64, torch.float32):
        args = (lat.to(dtype), torch.zeros(1, 16, 2, dtype=dtype), lat.flip(1).to(dtype), torch.ones(1, 16, dtype=bool),
                0.3, 1.0)
        ours, ref = sfm_kernel.social_force_velocities(*args, dt=0.25), sfm.social_force_velocities(*args, dt=0.25)
        assert float((ours - ref).abs().max()) <= BOUND * torch.finfo(dtype).eps


def test_hand_values():
    # test_sfm_model's hand computations of the goal force and the speed cap, through the kernel
    one = lambda p, v, g: [torch.tensor([[x]], dtype=torch.float64) for x in (p, v, g)] + [torch.ones(1, 1, dtype=bool)]
    cases = [(([0.0, 0.0], [0.0, 0.0], [4.0, 0.0]), [0.6, 0.0]), (([1.0, 1.0], [0.2, 0.4], [5.0, 1.0]), [0.7, 0.2]),
             (([0.0, 0.0], [3.0, 0.0], [0.0, -4.0]), [1.5 * 1.56 / math.hypot(1.5, 0.6), -0.6 * 1.56 / math.hypot(1.5, 0.6)]),
             (([0.0, 0.0], [0.4, 0.0], [0.1, 0.0]), [0.4 - 0.25 * 0.4 / 0.5, 0.0])]
    for (p, v, g), want in cases:
        got = sfm_kernel.social_force_velocities(*one(p, v, g), 0.3, 1.2, dt=0.25)
        torch.testing.assert_close(got[0, 0], torch.tensor(want, dtype=torch.float64))
    # a robot straight ahead brakes a human (Moussaid) and a robot on top pushes it away (body force)
    pos, vel, goal, valid = one([0.0, 0.0], [1.0, 0.0], [10.0, 0.0])
    free = sfm_kernel.social_force_velocities(pos, vel, goal, valid, 0.3, 1.0, dt=0.25)
    ahead = sfm_kernel.social_force_velocities(pos, vel, goal, valid, 0.3, 1.0, dt=0.25,
                                               others_pos=torch.tensor([[[1.0, 0.0]]], dtype=torch.float64),
                                               others_radius=0.3)
    assert ahead[0, 0, 0] < free[0, 0, 0]


def test_every_step_of_a_crowdnav_crowd_agrees():
    """A CrowdNav world of 20 social-force humans seeing the robot, run 40 steps with the torch model: at every
    step both backends decide the velocities from the same state, within BOUND eps. (Whole rollouts do not
    stay close: a 1e-6 m nudge of the starts grows to metres within 40 steps under either backend, the crowd
    at the circle's centre is chaotic; hence torch is the default backend.)"""
    from crowdbench.envs.crowdnav import CrowdNavConfig
    from crowdbench.envs.factory import crowdnav_world

    cfg = CrowdNavConfig(n_humans=20, humans="sfm", robot_visible=True, sfm_backend="numba")
    world, scen = crowdnav_world(cfg, 16)
    crowd = world.crowd
    assert crowd.backend == "numba"
    world.reset(torch.ones(16, dtype=torch.bool), scen.cases(range(16), "test"))
    g = torch.Generator().manual_seed(1)
    worst = 0.0
    for _ in range(40):
        new = {}
        for backend in ("numba", "torch"):
            crowd.backend = backend
            new[backend] = crowd.velocities(world.agents())
        worst = max(worst, float((new["numba"] - new["torch"]).abs().max()) / torch.finfo(torch.float32).eps)
        world.step(torch.rand(16, 1, 2, generator=g) - 0.5)  # (with torch: the reference trajectory)
    assert worst <= BOUND
    with pytest.raises(ValueError, match="sfm_backend"):
        CrowdNavConfig(humans="sfm", sfm_backend="jax")


def test_exp_and_atan2_within_one_ulp_of_math():
    import numba

    sfm_kernel._compile()
    exp, atan2 = sfm_kernel.fd_exp, sfm_kernel.fd_atan2

    @numba.njit
    def run(xs, ys, e, a):
        for k in range(xs.size):
            e[k] = exp(xs[k])
            a[k] = atan2(ys[k], xs[k])

    rng = np.random.default_rng(0)
    n = 300_000
    xs = np.concatenate([rng.uniform(-60, 10, n), rng.uniform(-2, 2, n), rng.uniform(-708, 709, n),
                         [0.0, -0.0, 1e-12, -1e-12, math.log(2) / 2, 1.5 * math.log(2), -708.0, 709.0]])
    ys = rng.normal(size=xs.size) * 10.0 ** rng.uniform(-6, 6, xs.size)
    ys[:6] = [0.0, -0.0, 1.0, -1.0, 0.0, -0.0]
    xs[:6] = [-1.0, -0.0, -0.0, 0.0, 0.0, 0.0]
    e, a = np.empty_like(xs), np.empty_like(xs)
    run(xs, ys, e, a)
    ref_e = np.array([math.exp(x) for x in xs])
    ref_a = np.array([math.atan2(y, x) for y, x in zip(ys, xs)])
    for got, ref in ((e, ref_e), (a, ref_a)):
        fin = ref != 0
        assert (np.abs(got[fin] - ref[fin]) <= np.spacing(np.abs(ref[fin]))).all()
        assert np.array_equal(got[~fin], ref[~fin]) and np.array_equal(np.signbit(got), np.signbit(ref))
    # atan2's signed zeros as C's (the first six arguments), exp's documented ends
    assert list(a[:6]) == [math.pi, -math.pi, math.pi / 2, -math.pi / 2, 0.0, -0.0]
    out = np.empty(3)
    run(np.array([-708.5, 710.0, math.nan]), np.zeros(3), out, np.empty(3))
    assert out[0] == 0.0 and out[1] == math.inf and math.isnan(out[2])


_RUN = r"""
import sys, numpy as np, torch
from crowdbench.envs.humans import sfm_kernel
sys.path.insert(0, sys.argv[2])
from test_sfm_kernel import KINDS, random_worlds
out = []
for i, kind in enumerate(KINDS):
    args, others = random_worlds(kind, 400, 12, 2, seed=i)
    out.append(sfm_kernel.social_force_velocities(*args, dt=0.25, **others).numpy())
from crowdbench.envs.crowdnav_cases import case_list
cases = case_list("circle", 20, n=60)["human_start"]
import numba
from crowdbench.envs import case_kernel
fns = (sfm_kernel._kernel, sfm_kernel._pair, sfm_kernel._human, *case_kernel.kernels())
asm = "".join(f.inspect_asm(sig) for f in fns for sig in f.signatures)
assert "mulss" in asm and "mulsd" in asm  # compiled here, not loaded from a cache (no code to inspect)
fma = any(op in asm for op in ("vfmadd", "vfmsub", "vfnmadd", "vfnmsub"))
sys.stdout.write((numba.config.CPU_NAME or "host") + (" FMA" if fma else ""))
np.save(sys.argv[1], np.concatenate([np.stack(out).ravel().astype(np.float64), cases.ravel()]))
"""


@pytest.mark.slow
def test_the_same_bytes_under_generic_and_host_targets(tmp_path):
    """The social-force kernel and CrowdNav's case sampler compiled for a generic x86-64 and for this CPU in two
    processes, each with its own (empty) cache: no FMA instruction in either, the same output bytes."""
    got = outputs_under_two_targets(tmp_path, _RUN, [str(ROOT / "tests")], timeout=900)
    assert got["generic"].tobytes() == got["host"].tobytes()
    assert np.isfinite(got["host"]).all()
