"""Seconds per RL episode: CrowdNav's own trainer beside crowdbench's ``algo=value`` (issue 32).

CrowdNav side (``--crowdnav PATH``): CrowdNav's ``crowd_nav/train.py`` loop, unchanged in substance, with
its own configs (SARL, invisible robot, 5 humans circle crossing, train.config), one torch thread, timed
around each RL episode: ``explorer.run_k_episodes(1, 'train', update_memory=True)`` +
``trainer.optimize_batch(100)`` (+ the target copy every 50 episodes), as train.py's while loop does. What
differs from train.py: the imitation phase is shortened (``--il-episodes``; its 50 SGD epochs are kept), the
validation at episode 0 runs ``--val-episodes`` of the 100 cases (timed separately, one by one), no
checkpoint files, no final test, and the env is ``CrowdSim()`` instead of ``gym.make('CrowdSim-v0')`` (old
gym's make returned the bare env; gym 0.26's make fails: its PassiveEnvChecker asserts an action space,
which CrowdSim does not define). Needs an interpreter that imports torch, numpy, gym, matplotlib and ``rvo2``.

crowdbench side (``--run RUN``): a value run's ``train_log.jsonl`` (rounds of ``algo.batch`` episodes;
``wall_s`` cumulative over the RL phase, snapshots included): seconds per episode and per step over the
rounds without a validation. ``--save``/``--load``: keep the CrowdNav figures in a JSON to compare with
later runs.

Set-up used (no network except PyPI; Python-RVO2 is not on PyPI under rvo2 / python-rvo2 / pyrvo2):

    git --git-dir=<a clone of github.com/vita-epfl/CrowdNav>/.git archive HEAD | tar -x -C /tmp/crowdnav-src
    python3.11 -m venv /tmp/cnvenv
    SP=/tmp/cnvenv/lib/python3.11/site-packages
    echo <the crowdbench venv>/lib/python3.11/site-packages > $SP/zz_workvenv.pth  # torch, numpy, matplotlib, pyrvo
    /tmp/cnvenv/bin/pip install gym==0.26.2                 # + gym_notices; cloudpickle comes from the .pth
    mkdir -p /tmp/cnshim && echo /tmp/cnshim > $SP/cnshim.pth   # /tmp/cnshim/rvo2.py: the shim below

/tmp/cnshim/rvo2.py (Python-RVO2's API on the ``pyrvo`` wheel, the same RVO2 2.0 C++; setters aliased,
getters return tuples as Python-RVO2's do; CrowdNav's ORCA reuses a simulator with a constant agent count, so
pyrvo's clear_agents caveat does not arise):

    import pyrvo
    class PyRVOSimulator(pyrvo.RVOSimulator):
        addAgent = pyrvo.RVOSimulator.add_agent
        doStep = pyrvo.RVOSimulator.do_step
        setAgentPrefVelocity = pyrvo.RVOSimulator.set_agent_pref_velocity
        setAgentPosition = pyrvo.RVOSimulator.set_agent_position
        setAgentVelocity = pyrvo.RVOSimulator.set_agent_velocity
        getNumAgents = pyrvo.RVOSimulator.get_num_agents
        def getAgentPosition(self, i): return self.get_agent_position(i).to_tuple()
        def getAgentVelocity(self, i): return self.get_agent_velocity(i).to_tuple()

No patch to CrowdNav's files. Run (both sides, then the ratios):

    OMP_NUM_THREADS=1 /tmp/cnvenv/bin/python benchmarks/crowdnav_trainer.py --crowdnav /tmp/crowdnav-src \
        --episodes 40 --run runs/value/sarl_value_query_s2 --save /tmp/crowdnav_times.json
    python benchmarks/crowdnav_trainer.py --load /tmp/crowdnav_times.json --run RUN   # compare another run

A crowdbench run with CrowdNav's RL settings (100 batches per episode, epsilon 0.5 -> 0.1 over 4,000, no
timeouts stored; the budget recipe's runs under runs/value use 20 batches), started beside the above,
without validation or the final test (its train_log.jsonl is RUN):

    OMP_NUM_THREADS=1 python -c "from pathlib import Path; from crowdbench.cli import compose
    from crowdbench.algos.value_train import train_value
    train_value(compose(['env=crowdnav', 'algo=value', 'cpus=1', 'algo.il_episodes=320',
        'algo.il_optimizer=adam', 'algo.il_lr=1e-3', 'algo.il_steps=3000', 'algo.episodes=160',
        'algo.val_every=0', 'algo.keep_best=false', 'seed=0']), Path('/tmp/cnbench/cb_run'))"
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")


def load(avg=None) -> str:
    """The 1, 5 and 15 minute load averages (now, or ``avg``)."""
    return "load " + " ".join(f"{x:.2f}" for x in (avg or os.getloadavg()))


def crowdnav_times(path: str, episodes: int, il_episodes: int, val_episodes: int, policy_name: str) -> dict:
    """Run CrowdNav's trainer (train.py's loop) from the checkout at ``path``; per-episode times and steps."""
    import configparser
    import logging

    sys.path.insert(0, path)
    import numpy as np
    import torch
    from crowd_nav.policy.policy_factory import policy_factory
    from crowd_nav.utils.explorer import Explorer
    from crowd_nav.utils.memory import ReplayMemory
    from crowd_nav.utils.trainer import Trainer
    from crowd_sim.envs import CrowdSim
    from crowd_sim.envs.utils.robot import Robot

    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    np.random.seed(0)
    configs = os.path.join(path, "crowd_nav", "configs")

    def config(name):
        c = configparser.RawConfigParser()
        c.read(os.path.join(configs, name))
        return c

    env_config, policy_config, tc = config("env.config"), config("policy.config"), config("train.config")
    policy = policy_factory[policy_name]()
    policy.configure(policy_config)
    policy.set_device(torch.device("cpu"))
    env = CrowdSim()
    env.configure(env_config)
    robot = Robot(env_config, "robot")
    env.set_robot(robot)
    memory = ReplayMemory(tc.getint("train", "capacity"))
    model = policy.get_model()
    trainer = Trainer(model, memory, torch.device("cpu"), tc.getint("trainer", "batch_size"))
    explorer = Explorer(env, robot, torch.device("cpu"), memory, policy.gamma, target_policy=policy)
    train_batches = tc.getint("train", "train_batches")
    eps_start, eps_end = tc.getfloat("train", "epsilon_start"), tc.getfloat("train", "epsilon_end")
    eps_decay, target_update = (
        tc.getfloat("train", "epsilon_decay"),
        tc.getint("train", "target_update_interval"),
    )

    def steps():
        return round(env.global_time / robot.time_step)

    # imitation learning (train.py's, with il_episodes demonstrations)
    out = {"load_start": os.getloadavg(), "policy": policy_name, "train_batches": train_batches}
    t0 = time.perf_counter()
    trainer.set_learning_rate(tc.getfloat("imitation_learning", "il_learning_rate"))
    il_policy = policy_factory[tc.get("imitation_learning", "il_policy")]()
    il_policy.multiagent_training = policy.multiagent_training
    il_policy.safety_space = 0 if robot.visible else tc.getfloat("imitation_learning", "safety_space")
    robot.set_policy(il_policy)
    explorer.run_k_episodes(il_episodes, "train", update_memory=True, imitation_learning=True)
    t1 = time.perf_counter()
    trainer.optimize_epoch(tc.getint("imitation_learning", "il_epochs"))
    out.update(
        il_episodes=il_episodes,
        il_collect_s=t1 - t0,
        il_fit_s=time.perf_counter() - t1,
        il_memory=len(memory),
    )
    explorer.update_target_model(model)
    print(
        f"CrowdNav imitation: {il_episodes} episodes {t1 - t0:.1f} s, fit {out['il_fit_s']:.1f} s  ({load()})"
    )

    # reinforcement learning (train.py's while loop; validation at episode 0 timed per episode)
    policy.set_env(env)
    robot.set_policy(policy)
    trainer.set_learning_rate(tc.getfloat("train", "rl_learning_rate"))
    out["load_val_start"] = os.getloadavg()
    val = []
    for _ in range(val_episodes):
        t, cpu = time.perf_counter(), time.process_time()
        explorer.run_k_episodes(1, "val", episode=0)
        val.append((time.perf_counter() - t, steps(), time.process_time() - cpu))
    out["val"], out["load_val_end"] = val, os.getloadavg()
    if val:
        print(
            f"CrowdNav validation: {sum(v[0] for v in val) / len(val):.3f} s/episode, "
            f"{sum(v[1] for v in val) / len(val):.1f} steps/episode over {len(val)}  ({load()})"
        )
    rl = []
    for episode in range(episodes):
        robot.policy.set_epsilon(
            eps_start + (eps_end - eps_start) / eps_decay * episode if episode < eps_decay else eps_end
        )
        t, cpu = time.perf_counter(), time.process_time()
        explorer.run_k_episodes(1, "train", update_memory=True, episode=episode)
        t_sample, n = time.perf_counter() - t, steps()
        trainer.optimize_batch(train_batches)
        if (episode + 1) % target_update == 0:
            explorer.update_target_model(model)
        rl.append((time.perf_counter() - t, t_sample, n, time.process_time() - cpu))
        print(
            f"  RL episode {episode:3d}: {rl[-1][0]:6.3f} s (sampling {t_sample:6.3f} s, {n:3d} steps; "
            f"{train_batches} batches {rl[-1][0] - t_sample:.3f} s; CPU {rl[-1][3]:.3f} s)  ({load()})"
        )
    out["rl"], out["load_end"] = rl, os.getloadavg()
    return out


def summarize_crowdnav(d: dict) -> tuple[float, float]:
    """Print CrowdNav's figures; return its seconds per RL episode and per step."""
    rl = d["rl"]
    total, sample, n, cpu = (sum(r[i] for r in rl) for i in range(4))
    print(
        f"CrowdNav ({d['policy']}, {d['train_batches']} batches/episode): {total / len(rl):.3f} s per RL episode "
        f"(median {statistics.median(r[0] for r in rl):.3f}; sampling {sample / len(rl):.3f} + training "
        f"{(total - sample) / len(rl):.3f}; CPU {cpu / len(rl):.3f}), {n / len(rl):.1f} steps/episode, "
        f"{1e3 * total / n:.1f} ms per step, over {len(rl)} episodes; "
        f"at start {load(d['load_start'])}, at end {load(d['load_end'])}"
    )
    if d.get("val"):
        v = d["val"]
        print(
            f"CrowdNav validation: {sum(x[0] for x in v) / len(v):.3f} s per episode "
            f"(CPU {sum(x[2] for x in v) / len(v):.3f}), "
            f"{sum(x[1] for x in v) / len(v):.1f} steps/episode over {len(v)}; "
            f"at start {load(d['load_val_start'])}, at end {load(d['load_val_end'])}"
        )
    return total / len(rl), total / n


def crowdbench_times(run: str) -> tuple[float, float]:
    """Seconds per RL episode and per step from a value run's train_log.jsonl (validation rounds left out)."""
    with open(os.path.join(run, "train_log.jsonl")) as f:
        rows = [json.loads(line) for line in f if line.strip()]
    rounds = [r for r in rows if "wall_s" in r]
    prev, kept = {"episodes": 0, "wall_s": 0.0, "frames": 0}, []
    for r in rounds:
        d_ep, d_s, d_fr = (
            r["episodes"] - prev["episodes"],
            r["wall_s"] - prev["wall_s"],
            r["frames"] - prev["frames"],
        )
        has_val = "val_success" in r
        print(
            f"  round to episode {r['episodes']:5d}: {d_s / d_ep:6.3f} s/episode, {d_fr / d_ep:5.1f} steps/episode"
            + ("  (validation in this round: left out)" if has_val else "")
        )
        if not has_val:
            kept.append((d_ep, d_s, d_fr))
        prev = r
    ep, s, fr = (sum(k[i] for k in kept) for i in range(3))
    per_round = [k[1] / k[0] for k in kept]
    print(
        f"crowdbench ({run}): {s / ep:.3f} s per RL episode (median round {statistics.median(per_round):.3f}), "
        f"{fr / ep:.1f} steps/episode, {1e3 * s / fr:.2f} ms per step, over {ep} episodes in {len(kept)} rounds"
    )
    return s / ep, s / fr


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--crowdnav", help="a CrowdNav checkout (work tree) to run")
    p.add_argument("--episodes", type=int, default=40, help="RL episodes of CrowdNav's trainer")
    p.add_argument(
        "--il-episodes", type=int, default=300, help="ORCA demonstrations before RL (CrowdNav: 3000)"
    )
    p.add_argument(
        "--val-episodes", type=int, default=10, help="validation episodes timed at episode 0 (CrowdNav: 100)"
    )
    p.add_argument("--policy", default="sarl")
    p.add_argument("--save", help="write CrowdNav's figures to this JSON")
    p.add_argument("--load", help="read CrowdNav's figures from this JSON instead of running it")
    p.add_argument("--run", help="a crowdbench value run directory (its train_log.jsonl)")
    a = p.parse_args()
    cn = None
    if a.crowdnav:
        d = crowdnav_times(a.crowdnav, a.episodes, a.il_episodes, a.val_episodes, a.policy)
        if a.save:
            with open(a.save, "w") as f:
                json.dump(d, f, indent=1)
    elif a.load:
        with open(a.load) as f:
            d = json.load(f)
    if a.crowdnav or a.load:
        cn = summarize_crowdnav(d)
    if a.run:
        cb = crowdbench_times(a.run)
        if cn is not None:
            print(
                f"ratio CrowdNav / crowdbench: {cn[0] / cb[0]:.1f}x per RL episode, {cn[1] / cb[1]:.1f}x per step"
            )


if __name__ == "__main__":
    main()
