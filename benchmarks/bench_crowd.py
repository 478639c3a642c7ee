"""Crowd throughput: env-steps/s of the world with reactive humans (ORCA, social force), of the
replay path before and after the world redesign, and of CrowdNav's own simulator side by side.

    python benchmarks/bench_crowd.py                                  # reactive + replay (new tree only)
    python benchmarks/bench_crowd.py --old-tree /tmp/wt-old           # + replay before the redesign
    python benchmarks/bench_crowd.py --crowdnav /tmp/crowdnav         # + CrowdNav's CrowdSim
    python benchmarks/bench_crowd.py --n-humans 5 --batch 64 --seconds 0.5 --threads 1   # quick

An env-step advances one environment by one step: ``B`` environments stepped once = ``B`` env-steps.

- **reactive world**: CrowdNav circle crossing (:func:`crowdnav_world`), humans ``orca`` / ``sfm``,
  robot invisible and visible, robot straight to its goal (``--robot random``: uniform in the speed
  disc). "world" = ``observe`` + ``step`` + partial reset of the finished environments by mask;
  "CrowdEnv" = the TorchRL env through ``step_and_maybe_reset``. Episodes cycle through a pool of
  ``--pool`` precomputed CrowdNav training cases, so the case generator (its cost printed
  separately; benchmarks/bench_cases.py) is not in the figures. Each row ends with the 1-minute load
  average when it was measured. CrowdNav's generator cannot place more than ~25 humans on its 4 m circle (each start
  and its antipodal goal need 0.8 m from every other start and goal; 30 never terminates): above
  ``--case-max`` humans the pool is placed here instead, evenly on a circle just big enough
  (:func:`ring_episodes`; 50 humans: radius 14.6 m), the robot crossing it from (0, -R) to (0, R).
- **replay**: protocol v1 on students001, the measurement of ``benchmarks/bench_env.py``
  (``core_rate``: observe + step + masked resets; ``torchrl_rate``: CrowdEnv ``step_and_maybe_reset``),
  run in a fresh process per tree; ``--old-tree`` (a checkout of the commit before the world redesign,
  e.g. ``git worktree add /tmp/wt-old 9451252``) runs that tree's own ``bench_env.py`` right after.
- **CrowdNav** (``--crowdnav DIR``, a checkout of github.com/vita-epfl/CrowdNav): its ``CrowdSim``
  (circle crossing, ORCA humans, invisible robot, robot ORCA or a fixed (0, 1) m/s action) for
  ``--crowdnav-steps`` steps, in a subprocess with a temporary ``rvo2`` shim over the ``pyrvo``
  wheel and, if ``gym`` is not installed, a stub of the two ``gym`` names it uses. Its figure
  is step calls only; resets (which run its case generator) are timed apart.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from crowdbench.baselines.straight import StraightToGoal
from crowdbench.envs.crowdnav import CrowdNavConfig
from crowdbench.envs.factory import crowdnav_world
from crowdbench.envs.observation import obs_tensordict
from crowdbench.envs.rules import RUNNING
from crowdbench.envs.torchrl_env import CrowdEnv

ROOT = Path(__file__).resolve().parents[1]


def timed(fn, seconds: float, warm: int = 2) -> tuple[int, float]:
    """``warm`` calls, then calls until ``seconds`` have passed (at least 2); (calls, elapsed)."""
    for _ in range(warm):
        fn()
    n, t0 = 0, time.perf_counter()
    while n < 2 or time.perf_counter() - t0 < seconds:
        fn()
        n += 1
    return n, time.perf_counter() - t0


# ----------------------------------------------------------------------------- episodes
def ring_episodes(n_pool: int, n_humans: int, spacing: float = 0.9, jitter: float = 0.04,
                  seed: int = 0) -> dict[str, torch.Tensor]:
    """Circle crossing for more humans than CrowdNav's generator places (speed tests only).

    ``2 n + 2`` slots evenly on a circle ``spacing`` m apart; the robot takes slot 0 -> its antipode
    and human ``k`` one of the other antipodal pairs (alternating sides), heading for the opposite
    point; every start is jittered by up to ``jitter`` m per axis (the goal stays its negative, as in
    CrowdNav), so starts and goals stay >= ``spacing - 2 sqrt(2) jitter`` m apart.
    """
    slots = 2 * n_humans + 2
    radius = spacing * slots / (2 * math.pi)
    k = torch.arange(1, n_humans + 1)
    slot = torch.where(k % 2 == 0, k, k + n_humans + 1)
    ang = -math.pi / 2 + 2 * math.pi * slot / slots
    ring = radius * torch.stack((ang.cos(), ang.sin()), -1)
    g = torch.Generator().manual_seed(seed)
    start = ring + jitter * (2 * torch.rand(n_pool, n_humans, 2, generator=g) - 1)
    robot = torch.tensor([[0.0, -radius]]).expand(n_pool, 1, 2)
    return {"start": robot.clone(), "goal": -robot, "human_start": start, "human_goal": -start}


def episode_pool(n_humans: int, n_pool: int, case_max: int) -> tuple[dict[str, torch.Tensor], str, float]:
    """(episodes, how they were made, seconds per episode to make them)."""
    t = time.perf_counter()
    if n_humans <= case_max:
        _, scenario = crowdnav_world(CrowdNavConfig(n_humans=n_humans), 1)
        pool = scenario.cases(range(n_pool), "train")
        how = "CrowdNav training cases"
    else:
        pool = ring_episodes(n_pool, n_humans)
        how = f"ring r={pool['goal'][0, 0, 1]:.1f} m"
    return pool, how, (time.perf_counter() - t) / n_pool


class Cycle:
    """Episodes ``i, i + 1, ...`` of a pool, wrapping around (as CrowdEnv's fixed list does)."""

    def __init__(self, pool: dict[str, torch.Tensor]):
        self.pool, self.next = pool, 0

    def __call__(self, n: int) -> dict[str, torch.Tensor]:
        idx = (self.next + torch.arange(n)) % len(self.pool["start"])
        self.next += n
        return {k: v[idx] for k, v in self.pool.items()}


def robot_policy(kind: str, v_max: float, dt: float):
    """``act(td)`` -> ``[B, 1, 2]``: straight to the goal (observation frame) or uniform in the speed disc."""
    if kind == "straight":
        return StraightToGoal(v_max, dt).act
    gen = torch.Generator().manual_seed(0)

    def act(td):
        b = td.batch_size[0]
        r = v_max * torch.rand(b, 1, 1, generator=gen).sqrt()
        a = 2 * math.pi * torch.rand(b, 1, 1, generator=gen)
        return torch.cat((r * a.cos(), r * a.sin()), -1)

    return act


# ----------------------------------------------------------------------------- reactive world
def world_rate(cfg: CrowdNavConfig, batch: int, pool: dict, seconds: float, robot: str) -> float:
    world, _ = crowdnav_world(cfg, batch)
    draw = Cycle(pool)
    world.reset(torch.ones(batch, dtype=torch.bool), draw(batch))
    act = robot_policy(robot, cfg.v_max, cfg.dt)

    def step():
        world.step(act(obs_tensordict(world.observe(), batch)))
        done = (world.outcome != RUNNING).any(-1)
        if done.any():  # partial reset by mask, as the TorchRL env does
            world.reset(done, draw(int(done.sum())))

    n, dt = timed(step, seconds)
    return n * batch / dt


def env_rate(cfg: CrowdNavConfig, batch: int, pool: dict, seconds: float, robot: str) -> float:
    world, scenario = crowdnav_world(cfg, batch)
    env = CrowdEnv(world, scenario, seed=0, episodes=pool)
    act = robot_policy(robot, cfg.v_max, cfg.dt)
    state = {"td": env.reset()}

    def step():
        td = state["td"]
        td["agents", "action"] = act(td)
        _, state["td"] = env.step_and_maybe_reset(td)

    n, dt = timed(step, seconds)
    return n * batch / dt


# ----------------------------------------------------------------------------- replay (bench_env.py)
_REPLAY = """
import importlib.util, json, sys, torch
torch.set_num_threads({threads})
spec = importlib.util.spec_from_file_location("tree_bench_env", {path!r})
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
from crowdbench.data.scenes import load_scene
core = mod.core_rate(load_scene("students001"), {batch}, {seconds})
env = mod.torchrl_rate({batch}, {seconds})
print(json.dumps({{"core": core, "torchrl": env}}))
"""


def replay_rates(tree: Path, batch: int, seconds: float, threads: int) -> dict[str, float]:
    """``bench_env.py``'s core and TorchRL rates on students001, run from ``tree`` in a fresh process."""
    code = _REPLAY.format(threads=threads, path=str(tree / "benchmarks" / "bench_env.py"), batch=batch,
                          seconds=seconds)
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=tree, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- CrowdNav
RVO2_SHIM = '''
"""Python-RVO2's ``rvo2`` names used by CrowdNav, over the ``pyrvo`` wheel (benchmark shim)."""
import pyrvo


def _v(x):
    return (float(x[0]), float(x[1]))


class PyRVOSimulator:
    def __init__(self, timeStep, neighborDist, maxNeighbors, timeHorizon, timeHorizonObst, radius, maxSpeed,
                 velocity=(0.0, 0.0)):
        self._s = pyrvo.RVOSimulator(float(timeStep), float(neighborDist), int(maxNeighbors), float(timeHorizon),
                                     float(timeHorizonObst), float(radius), float(maxSpeed),
                                     pyrvo.Vector2(*_v(velocity)))

    def addAgent(self, pos, neighborDist=None, maxNeighbors=None, timeHorizon=None, timeHorizonObst=None,
                 radius=None, maxSpeed=None, velocity=(0.0, 0.0)):
        if neighborDist is None:
            return self._s.add_agent(_v(pos))
        return self._s.add_agent(_v(pos), float(neighborDist), int(maxNeighbors), float(timeHorizon),
                                 float(timeHorizonObst), float(radius), float(maxSpeed), _v(velocity))

    def setAgentPrefVelocity(self, i, v):
        self._s.set_agent_pref_velocity(int(i), _v(v))

    def setAgentPosition(self, i, p):
        self._s.set_agent_position(int(i), _v(p))

    def setAgentVelocity(self, i, v):
        self._s.set_agent_velocity(int(i), _v(v))

    def doStep(self):
        self._s.do_step()

    def getAgentPosition(self, i):
        return self._s.get_agent_position(int(i)).to_tuple()

    def getAgentVelocity(self, i):
        return self._s.get_agent_velocity(int(i)).to_tuple()

    def getNumAgents(self):
        return self._s.get_num_agents()

    def getGlobalTime(self):
        return self._s.get_global_time()
'''

GYM_STUB = {
    "gym/__init__.py": "class Env:\n    metadata = {}\n",
    "gym/envs/__init__.py": "",
    "gym/envs/registration.py": "def register(**kwargs):\n    pass\n",
}

CROWDNAV_RUN = '''
import configparser, json, logging, sys, time
import numpy as np
logging.disable(logging.INFO)
from crowd_sim.envs.crowd_sim import CrowdSim
from crowd_sim.envs.observation.orca import ORCA
from crowd_sim.envs.utils.action import ActionXY
from crowd_sim.envs.utils.robot import Robot

crowdnav, n_humans, steps, policy = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
config = configparser.RawConfigParser()
config.read(f"{crowdnav}/crowd_nav/configs/env.config")
config.set("sim", "human_num", str(n_humans))
config.set("sim", "test_sim", "circle_crossing")
config.set("robot", "visible", "false")
env = CrowdSim()
env.configure(config)
robot = Robot(config, "robot")
robot.set_policy(ORCA())
robot.policy.safety_space = 0  # as crowd_nav/test.py
env.set_robot(robot)
fixed = ActionXY(0.0, robot.v_pref)  # straight to the goal: (0, -4) -> (0, 4)
t_step = t_reset = 0.0
episodes = 0
t = time.perf_counter()
ob = env.reset("test")
t_reset += time.perf_counter() - t
for _ in range(steps):
    t = time.perf_counter()
    action = robot.act(ob) if policy == "orca" else fixed
    ob, reward, done, info = env.step(action)
    t_step += time.perf_counter() - t
    if done:
        episodes += 1
        t = time.perf_counter()
        ob = env.reset("test")
        t_reset += time.perf_counter() - t
print(json.dumps({"steps": steps, "t_step": t_step, "t_reset": t_reset, "episodes": episodes}))
'''


def crowdnav_rates(crowdnav: Path, n_humans: int, steps: int, policy: str, tmp: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join((str(tmp), str(crowdnav))), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, str(tmp / "run_crowdnav.py"), str(crowdnav), str(n_humans), str(steps),
                          policy], check=False, env=env, capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"CrowdNav run failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def prepare_crowdnav(tmp: Path) -> str:
    """Write the rvo2 shim, the runner and (if gym is missing) the gym stub into ``tmp``; say which gym."""
    (tmp / "rvo2.py").write_text(RVO2_SHIM)
    (tmp / "run_crowdnav.py").write_text(CROWDNAV_RUN)
    has_gym = subprocess.run([sys.executable, "-c", "import gym"], check=False, capture_output=True).returncode == 0
    if has_gym:
        return "installed gym"
    for name, text in GYM_STUB.items():
        (tmp / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp / name).write_text(text)
    return "gym stubbed (Env, envs.registration.register)"


# ----------------------------------------------------------------------------- main
def ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--humans", default="orca,sfm", help="crowd models")
    ap.add_argument("--n-humans", type=ints, default=[5, 20, 50])
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--threads", type=ints, default=[1, 2])
    ap.add_argument("--seconds", type=float, default=3.0, help="timed seconds per figure (after warm-up)")
    ap.add_argument("--robot", choices=("straight", "random"), default="straight")
    ap.add_argument("--visible", default="false,true", help="robot visible to the humans: false,true")
    ap.add_argument("--paths", default="world,env")
    ap.add_argument("--pool", type=int, default=32, help="precomputed episodes the resets cycle through")
    ap.add_argument("--case-max", type=int, default=20, help="most humans placed by CrowdNav's case generator")
    ap.add_argument("--single", action="store_true", help="also B = 1 (ORCA, invisible robot), as CrowdNav runs")
    ap.add_argument("--replay-batch", type=int, default=1024, help="0: skip the replay part")
    ap.add_argument("--old-tree", type=Path, default=None, help="checkout before the world redesign (9451252)")
    ap.add_argument("--crowdnav", type=Path, default=None, help="a CrowdNav checkout (github.com/vita-epfl/CrowdNav)")
    ap.add_argument("--crowdnav-humans", type=ints, default=[5, 20])
    ap.add_argument("--crowdnav-steps", type=int, default=400)
    ap.add_argument("--crowdnav-policy", default="orca,fixed")
    ap.add_argument("--skip-reactive", action="store_true")
    ap.add_argument("--orca-backend", default="numba,torch", help="ORCA solvers: numba (compiled), torch")
    ap.add_argument("--sfm-backend", default="numba,torch", help="social force: numba (compiled), torch")
    ap.add_argument("--pyrvo", action="store_true", help="also a Python loop over pyrvo simulators (ORCA rows)")
    args = ap.parse_args(argv)

    load = os.getloadavg()
    print(f"torch {torch.__version__}, cores {os.cpu_count()}, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, "
          f"robot {args.robot}, timed {args.seconds} s per figure")
    visible = [v.strip() == "true" for v in args.visible.split(",")]
    paths = args.paths.split(",")
    fns = {"world": world_rate, "env": env_rate}
    names = {"world": "world (observe + step + masked reset)", "env": "TorchRL CrowdEnv (step_and_maybe_reset)"}

    if not args.skip_reactive:
        pools = {}
        print("\nEpisode pools (resets cycle through them):")
        for n in args.n_humans:
            pools[n] = episode_pool(n, args.pool, args.case_max)
            print(f"  {n} humans: {args.pool} episodes, {pools[n][1]}, {pools[n][2] * 1e3:.1f} ms per episode to make")
        print("\n| humans | M | robot visible | path | threads | B | env-steps/s | us per env-step | load |")
        print("|---|---|---|---|---|---|---|---|---|")
        backends = {"orca": args.orca_backend.split(","), "sfm": args.sfm_backend.split(",")}
        models = [(h, be) for h in args.humans.split(",") for be in backends[h]]
        runs = [(h, be, n, v, p, t, args.batch) for h, be in models for n in args.n_humans for v in visible
                for p in paths for t in args.threads]
        if args.single:
            runs += [("orca", be, n, False, p, 1, 1) for _, be in models if _ == "orca" for n in args.n_humans
                     for p in paths]
        for h, be, n, v, p, t, b in runs:
            torch.set_num_threads(t)
            cfg = CrowdNavConfig(humans=h, n_humans=n, robot_visible=v, **{f"{h}_backend": be})
            r = fns[p](cfg, b, pools[n][0], args.seconds, args.robot)
            print(f"| {h} ({be}) | {n} | {'yes' if v else 'no'} | {names[p]} | {t} | {b} | {r:,.0f} | {1e6 / r:.1f} | "
                  f"{os.getloadavg()[0]:.1f} |", flush=True)
        if args.pyrvo:
            from pyrvo_loop import pyrvo_rate

            for n in args.n_humans:
                for t in args.threads:
                    cfg = CrowdNavConfig(n_humans=n)
                    r = pyrvo_rate(pools[n][0], args.batch, t, args.seconds, cfg.dt, cfg.human_radius
                                   + cfg.orca_radius_margin, cfg.human_v_pref, cfg.orca)
                    print(f"| orca (Python loop over pyrvo, {t} process(es)) | {n} | yes | set pref + do_step + "
                          f"read back | {t} | {args.batch} | {r:,.0f} | {1e6 / r:.1f} | {os.getloadavg()[0]:.1f} |",
                          flush=True)

    if args.replay_batch:
        B = args.replay_batch
        trees = [("after (world API)", ROOT)] + ([("before (9451252)", args.old_tree)] if args.old_tree else [])
        print(f"\nReplay, students001, B = {B} (bench_env.py's measurement, fresh process per tree, back to back):")
        print("| tree | threads | core env-steps/s | TorchRL CrowdEnv env-steps/s |")
        print("|---|---|---|---|")
        for t in args.threads:
            for name, tree in trees:
                r = replay_rates(tree, B, args.seconds, t)
                print(f"| {name} | {t} | {r['core']:,.0f} | {r['torchrl']:,.0f} |", flush=True)

    if args.crowdnav is None:
        print("\nCrowdNav: skipped (pass --crowdnav DIR, a checkout of github.com/vita-epfl/CrowdNav)")
    elif not (args.crowdnav / "crowd_sim" / "envs" / "crowd_sim.py").exists():
        print(f"\nCrowdNav: skipped ({args.crowdnav} has no crowd_sim/envs/crowd_sim.py)")
    else:
        with tempfile.TemporaryDirectory() as tmp:
            how = prepare_crowdnav(Path(tmp))
            print(f"\nCrowdNav CrowdSim ({args.crowdnav}; rvo2 shim over pyrvo, {how}): circle crossing, ORCA humans, "
                  f"invisible robot, {args.crowdnav_steps} steps, one environment, single thread")
            print("| humans | robot policy | env-steps/s (step calls) | ms per step | episodes | ms per reset |")
            print("|---|---|---|---|---|---|")
            for n in args.crowdnav_humans:
                for pol in args.crowdnav_policy.split(","):
                    r = crowdnav_rates(args.crowdnav, n, args.crowdnav_steps, pol, Path(tmp))
                    resets = r["episodes"] + 1
                    print(f"| {n} | {pol} | {r['steps'] / r['t_step']:,.0f} | {r['t_step'] / r['steps'] * 1e3:.2f} | "
                          f"{r['episodes']} | {r['t_reset'] / resets * 1e3:.1f} |", flush=True)
    load = os.getloadavg()
    print(f"\nload average at the end {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    main()
