"""Speed of the encoders and heads on real STUDENTS001 observations, and how often the
neighbour cap K binds.

    python benchmarks/bench_models.py                 # 2 threads, allocator tuned
    python benchmarks/bench_models.py --threads 1 --no-tune-allocator --quick

Reports (medians over repetitions, milliseconds):

- graph construction, receptive-field vs full layout;
- forward + backward of every encoder preset at batch 100 (graph built inside, and with
  the graph prepared beforehand), gatedgcn also in the full layout;
- one TD3 update at batch 100 (target actor + 2 target critics, 2 critics fwd/bwd, actor +
  critic fwd/bwd, Adam, Polyak), hand-written and with TorchRL's ``TD3Loss`` (vmapped and
  ``deactivate_vmap=True`` critics); targets: <= 30 ms for the fast gatedgcn preset;
- actor decision latency at B = 1 on a crowded observation (target <= 1 ms);
- the K-cap binding rate on STUDENTS001 / STUDENTS003;
- ``crowd``: forward + backward of each registered encoder's preset (``--encoders`` to choose)
  at B = 256 with M = 40 observed humans within 5 m (synthetic, uniform in the sensing disc).

Timings on a shared machine are noisy: the script prints the load average and the CPU
used by other processes while it ran.
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import time
from pathlib import Path

import torch
import yaml

from crowdbench.baselines.straight import StraightToGoal
from crowdbench.envs.factory import replay_world
from crowdbench.envs.observation import obs_tensordict
from crowdbench.models import make_encoder
from crowdbench.models.graph import build_graph, cap_binding
from crowdbench.models.heads import (
    Actor,
    Critic,
    actor_module,
    critic_module,
    prepare_batch,
    trace_for_inference,
)
from crowdbench.models.perf import tune_allocator

CONFIGS = Path(__file__).resolve().parents[1] / "crowdbench" / "conf" / "encoder"


def bench(fn, reps: int, warm: int = 3) -> float:
    for _ in range(warm):
        fn()
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t) * 1e3)
    return statistics.median(ts)


def cpu_busy() -> tuple[float, float]:
    """(total busy jiffies, this process's jiffies) to estimate other processes' CPU use."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    with open("/proc/self/stat") as f:
        s = f.read().rsplit(")", 1)[1].split()
    return sum(v) - v[3] - v[4], int(s[11]) + int(s[12])


def rollout_obs(scene: str, b: int, steps: int, seed: int = 0):
    """Observations ``steps`` steps into ``b`` straight-to-goal episodes (random starts)."""
    g = torch.Generator().manual_seed(seed)
    sim, scenario = replay_world(scene, b)
    t0 = torch.randint(0, scenario.last_start + 1, (b,), generator=g)
    ang = torch.rand(b, generator=g) * 2 * torch.pi
    sim.reset(torch.ones(b, dtype=torch.bool), scenario.episodes(t0, ang))
    pol = StraightToGoal()
    for _ in range(steps):
        sim.step(pol.act(obs_tensordict(sim.observe(), b)))
    return sim, pol


def transition(scene: str, b: int, seed: int = 0):
    sim, _ = rollout_obs(scene, b, steps=8, seed=seed)
    o = sim.observe()
    a = torch.rand(b, 1, 2) * 2 - 1
    info = sim.step(a)
    o2 = sim.observe()
    return o, a, info, o2


def preset(name: str) -> dict:
    return yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())


# ----------------------------------------------------------------------------- sections
def graph_section(o, reps):
    args = (o["robot"], o["humans"], o["humans_mask"])
    print("\n## graph construction, batch 100 STUDENTS001 (ms)")
    for rf in (True, False):
        t = bench(lambda rf=rf: build_graph(*args, receptive_field=rf), reps)
        g = build_graph(*args, receptive_field=rf)
        print(f"  {'receptive-field' if rf else 'full':16s} rows x slots = {tuple(g.nbr.shape[1:])}  {t:7.2f}")
    print(f"  observed humans per robot: mean {o['humans_mask'].sum(-1).float().mean():.1f}, "
          f"max {int(o['humans_mask'].sum(-1).max())} (M = {o['humans'].shape[-2]} slots)")


def encoder_section(o, reps, quick):
    args = (o["robot"], o["humans"], o["humans_mask"])
    print("\n## encoder forward + backward, batch 100 (ms): graph built inside | graph prepared")
    rows = [
        ("gatedgcn (paper, D=256)", preset("gatedgcn"), {}),
        ("gatedgcn (D=32)", preset("gatedgcn"), {}),
        ("gatedgcn D=64", preset("gatedgcn"), {"dim": 64}),
        ("gatedgcn (D=32), full layout", preset("gatedgcn"), {"receptive_field": False}),
        ("gatedgcn paper, full layout", preset("gatedgcn"), {"receptive_field": False}),
        ("gcn (D=256)", preset("gcn"), {}),
        ("gcn D=32", preset("gcn"), {"dim": 32}),
        ("mlp (D=256)", preset("mlp"), {}),
        ("mlp D=32", preset("mlp"), {"dim": 32, "hidden": [32, 32]}),
    ]
    for label, cfg, over in rows:
        if quick and "full" in label and "paper" in label:
            continue
        enc = make_encoder(**{**cfg, **over})
        prep = enc.prepare(*args)
        n = max(3, reps // 4) if "full" in label or "256" in label else reps

        def raw(enc=enc):
            enc(*args)[1].sum().backward()

        def pre(enc=enc, prep=prep):
            enc.forward_prepared(prep)[1].sum().backward()

        print(f"  {label:30s} {bench(raw, n):8.2f} | {bench(pre, n):8.2f}")


def crowd_obs(b: int = 256, m: int = 40, radius: float = 5.0, seed: int = 0):
    """``b`` robots at the origin (goal 4 m ahead), each with ``m`` observed humans uniform in the disc."""
    g = torch.Generator().manual_seed(seed)
    r = radius * torch.rand(b, 1, m, generator=g).sqrt()
    ang = 2 * torch.pi * torch.rand(b, 1, m, generator=g)
    vel = torch.randn(b, 1, m, 2, generator=g) * 0.5
    humans = torch.cat((torch.stack((r * ang.cos(), r * ang.sin()), -1), vel), -1)
    robot = torch.tensor([0.0, 0.0, 0.5, 0.0, 4.0, 0.0]).expand(b, 1, 6).clone()
    return robot, humans, torch.ones(b, 1, m, dtype=torch.bool)


def crowd_section(reps, names=None):
    from crowdbench.models import ENCODERS

    args = crowd_obs()
    print("\n## encoder forward + backward, B = 256, M = 40 observed humans within 5 m, presets (ms)")
    for name in names or list(ENCODERS):
        enc = make_encoder(**preset(name))

        def step(enc=enc):
            enc(*args)[1].sum().backward()

        n_par = sum(p.numel() for p in enc.parameters())
        print(f"  {name:10s} D={enc.out_dim:<4d} {n_par:7d} params {bench(step, reps):8.2f}")


def adam(params):
    """Adam as TD3 uses it; ``fused=True`` is the fast CPU implementation (one kernel)."""
    return torch.optim.Adam(params, lr=1e-3, fused=True)


def td3_manual(name_cfg, o, a, info, o2, actor_update: bool = True, stored_graphs: bool = False):
    actor = Actor(make_encoder(**name_cfg))
    c1, c2 = Critic(make_encoder(**name_cfg)), Critic(make_encoder(**name_cfg))
    ta, t1, t2 = copy.deepcopy(actor), copy.deepcopy(c1), copy.deepcopy(c2)
    opt_a = adam(actor.parameters())
    opt_c = adam([*c1.parameters(), *c2.parameters()])
    r, d = info.reward.unsqueeze(-1), info.terminated.unsqueeze(-1).float()
    enc = actor.encoder
    nets = [(actor, ta), (c1, t1), (c2, t2)]
    pairs = [(list(t.parameters()), list(n.parameters())) for n, t in nets]

    stored = (enc.prepare(o["robot"], o["humans"], o["humans_mask"]), enc.prepare(o2["robot"], o2["humans"], o2["humans_mask"]))

    def update():
        if stored_graphs:  # graphs prepared at collection time and sampled from the buffer
            p, p2 = stored
        else:  # one graph per batch (obs and next obs), shared by all six networks
            p = enc.prepare(o["robot"], o["humans"], o["humans_mask"])
            p2 = enc.prepare(o2["robot"], o2["humans"], o2["humans_mask"])
        with torch.no_grad():
            na = (ta.forward_prepared(p2) + (0.2 * torch.randn_like(a)).clamp(-0.5, 0.5)).clamp(-1, 1)
            y = r + 0.99 * (1 - d) * torch.minimum(t1.forward_prepared(p2, na), t2.forward_prepared(p2, na))
        lc = (c1.forward_prepared(p, a) - y).square().mean() + (c2.forward_prepared(p, a) - y).square().mean()
        opt_c.zero_grad()
        lc.backward()
        opt_c.step()
        if not actor_update:  # TD3's delayed policy update: critic-only steps
            return
        with torch.no_grad():  # the critic's state is a constant for the actor loss
            h1 = c1.encoder.forward_prepared(p)[1]
        la = -c1.q(h1, actor.forward_prepared(p)).mean()
        opt_a.zero_grad()
        la.backward()
        opt_a.step()
        with torch.no_grad():
            for tp, np_ in pairs:
                torch._foreach_lerp_(tp, np_, 0.005)

    return update


def td3_torchrl(name_cfg, o, a, info, o2, deactivate_vmap):
    from tensordict import TensorDict
    from torchrl.objectives import SoftUpdate, TD3Loss

    b = a.shape[0]
    td = TensorDict(
        {
            "agents": {"observation": o, "action": a},
            "next": {
                "agents": {
                    "observation": o2,
                    "reward": info.reward.unsqueeze(-1),
                    "done": (info.terminated | info.truncated).unsqueeze(-1),
                    "terminated": info.terminated.unsqueeze(-1),
                }
            },
        },
        batch_size=[b],
    )
    actor, critic = Actor(make_encoder(**name_cfg)), Critic(make_encoder(**name_cfg))
    loss = TD3Loss(
        actor_module(actor, prepared=True),
        critic_module(critic, prepared=True),
        bounds=(-1.0, 1.0),
        num_qvalue_nets=2,
        deactivate_vmap=deactivate_vmap,
    )
    loss.set_keys(
        action=("agents", "action"),
        state_action_value=("agents", "state_action_value"),
        reward=("agents", "reward"),
        done=("agents", "done"),
        terminated=("agents", "terminated"),
    )
    loss.make_value_estimator(gamma=0.99)
    upd = SoftUpdate(loss, tau=0.005)
    opt = adam(loss.parameters())

    def update():
        batch = prepare_batch(td.clone(False), actor.encoder, critic.encoder)
        out = loss(batch)
        opt.zero_grad()
        (out["loss_actor"] + out["loss_qvalue"]).backward()
        opt.step()
        upd.step()

    return update


def td3_section(o, a, info, o2, reps, quick):
    print("\n## one TD3 update, batch 100 (ms) — target <= 30 ms for gatedgcn (D=32)")
    print("   hand-written: graph prepared once per batch and shared by the 6 networks, target actor")
    print("   + 2 target critics, 2 critics fwd/bwd, actor fwd/bwd through critic 1, fused Adam,")
    print("   Polyak. 'delay 2': mean of a critic-only and a full step (TD3 policy delay d = 2).")
    print("   'stored': graphs prepared at collection time and kept in the replay buffer.")
    print("   TD3Loss: TorchRL's loss with the prepared modules (vmapped critics / deactivate_vmap).")
    cfgs = [("gatedgcn (D=32)", preset("gatedgcn")), ("gatedgcn D=64", {**preset("gatedgcn"), "dim": 64})]
    if not quick:
        cfgs += [
            ("gcn D=32", {**preset("gcn"), "dim": 32}),
            ("mlp D=32", {**preset("mlp"), "dim": 32, "hidden": [32, 32]}),
            ("gatedgcn (paper, D=256)", preset("gatedgcn")),
        ]
    head = ["hand-written", "delay 2", "stored+d2", "TD3Loss vmap", "TD3Loss loop"]
    print(f"  {'encoder':24s}" + "".join(f"{h:>14s}" for h in head))
    for label, cfg in cfgs:
        n = max(3, reps // 4) if "256" in label else reps
        t0 = bench(td3_manual(cfg, o, a, info, o2), n)
        tc = bench(td3_manual(cfg, o, a, info, o2, actor_update=False), n)
        s0 = bench(td3_manual(cfg, o, a, info, o2, stored_graphs=True), n)
        sc = bench(td3_manual(cfg, o, a, info, o2, actor_update=False, stored_graphs=True), n)
        t1 = bench(td3_torchrl(cfg, o, a, info, o2, False), n)
        t2 = bench(td3_torchrl(cfg, o, a, info, o2, True), n)
        row = [t0, (t0 + tc) / 2, (s0 + sc) / 2, t1, t2]
        print(f"  {label:24s}" + "".join(f"{x:14.2f}" for x in row))


def latency_section(reps, rounds: int = 5):
    print("\n## actor decision latency, B = 1, raw observation -> action (ms) — target <= 1 ms")
    print("   round-robin over the models; median of each round, then min / median over rounds")
    sim, _ = rollout_obs("students001", 256, steps=8, seed=1)
    o = sim.observe()
    i = int(o["humans_mask"].sum(-1).argmax())
    one = {k: v[i : i + 1] for k, v in o.items()}
    print(f"  observation with {int(one['humans_mask'].sum())} observed humans (M = {one['humans'].shape[-2]})")
    models = {
        "gatedgcn (D=32)": preset("gatedgcn"),
        "gatedgcn paper": preset("gatedgcn"),
        "gcn": preset("gcn"),
        "mlp": preset("mlp"),
    }
    actors = {k: Actor(make_encoder(**cfg)).eval() for k, cfg in models.items()}
    obs = (one["robot"], one["humans"], one["humans_mask"])
    actors["gatedgcn (D=32) traced"] = trace_for_inference(actors["gatedgcn (D=32)"], *obs)
    actors["gatedgcn paper traced"] = trace_for_inference(actors["gatedgcn paper"], *obs)
    times: dict = {k: [] for k in actors}
    for _ in range(rounds):
        for k, actor in actors.items():

            def act(actor=actor):
                with torch.inference_mode():
                    actor(*obs)

            times[k].append(bench(act, reps * 10, warm=20))
    for k, ts in times.items():
        print(f"  {k:22s} min {min(ts):6.3f}   median {statistics.median(ts):6.3f}")


def cap_section(k_values=(4, 6, 8, 12)):
    print("\n## K-cap binding (fraction of observed nodes with more than K candidate neighbours)")
    for scene in ("students001", "students003"):
        sim, pol = rollout_obs(scene, 500, steps=0, seed=2)
        obs = []
        for _ in range(40):  # 40 steps of 500 straight-to-goal episodes
            o = sim.observe()
            obs.append(o)
            sim.step(pol.act(obs_tensordict(o, 500)))
        cat = {key: torch.cat([x[key] for x in obs]) for key in obs[0]}
        parts = []
        for k in k_values:
            s = cap_binding(cat["robot"], cat["humans"], cat["humans_mask"], k=k)
            parts.append(f"K={k}: {100 * s['nodes']:.2f}% (robot {100 * s['robot']:.2f}%)")
        s = cap_binding(cat["robot"], cat["humans"], cat["humans_mask"])
        print(f"  {scene:12s} " + "  ".join(parts))
        print(f"  {'':12s} mean degree {s['mean_degree']:.2f}, max {s['max_degree']:.0f}, {s['n_nodes']} nodes")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--quick", action="store_true", help="skip the slowest configurations")
    ap.add_argument("--no-tune-allocator", action="store_true")
    ap.add_argument("--sections", default="graph,encoders,td3,latency,cap,crowd")
    ap.add_argument("--encoders", default=None, help="comma-separated encoders of the crowd section (default all)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    tuned = False if args.no_tune_allocator else tune_allocator()
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, allocator tuned: {tuned}, "
          f"load average before: {os.getloadavg()[0]:.2f}")
    busy0, self0 = cpu_busy()
    wall0 = time.perf_counter()
    o, a, info, o2 = transition("students001", 100)
    sections = args.sections.split(",")
    if "graph" in sections:
        graph_section(o, args.reps)
    if "encoders" in sections:
        encoder_section(o, args.reps, args.quick)
    if "td3" in sections:
        td3_section(o, a, info, o2, args.reps, args.quick)
    if "latency" in sections:
        latency_section(args.reps)
    if "cap" in sections:
        cap_section()
    if "crowd" in sections:
        crowd_section(args.reps, args.encoders.split(",") if args.encoders else None)
    busy1, self1 = cpu_busy()
    hz = os.sysconf("SC_CLK_TCK")
    wall = time.perf_counter() - wall0
    other = max(0.0, (busy1 - busy0) - (self1 - self0)) / hz / wall
    print(f"\nother processes used {other:.2f} CPU cores on average during the run "
          f"(load average after: {os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
