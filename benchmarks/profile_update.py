"""Where the time of one TD3 update goes: ``OffPolicyAlgorithm.update`` as ``crowdbench run`` makes it.

    python benchmarks/profile_update.py                                  # timings, every encoder
    python benchmarks/profile_update.py --encoders gatedgcn,sarl --profile
    python benchmarks/profile_update.py --overrides "algo.batch_size=256"

The default recipe (``algo=td3``, uniform replay, lookahead critic 0.25 s, batch 100) on a
uniform buffer of real students001 transitions. TD3 updates the actor every 2nd step, so the
cost per update is the mean of a critic-only step and a full step (critics + actor + targets).
Rounds alternate between the encoders, so that a burst of load on the shared machine hits all
of them; the figure is the median over rounds of each round's median. ``--profile`` adds, per
encoder, the top operators of ``torch.profiler`` (self CPU time) and the top Python functions of
``cProfile`` over one critic-only + one full step.

The "before" figures below were taken with the version of this script that drove ``Learner`` (before the algorithm components)
(git history), on the revision before the changes.

Measured (1 thread, 2-core machine shared with other jobs, load average 0.7-1.0, medians over
2-3 runs; ms per update, before -> after; "compact" is the opt-in ``make_encoder(compact=True)``):

    gatedgcn 69 -> 59   sarl 59 -> 59 (compact 34)   lstm_rl 235 -> 60   rgl 124 -> 116 (compact 51)
    gat      65 -> 53   dsrnn 36 -> 33 (compact 24)

Where the time went before: the critic term's forward (four fifths of it the two vmapped
critic calls, target and current) and backward; for lstm_rl the backward of its vmapped cell
loop (``aten::fill_`` + ``add_`` of M full-size zero gradients, 45% + 21% of the CPU time); for
gatedgcn and gat the lookahead critic's graph built under vmap for both copies (``topk``, the
``[2, B, ...]`` gathers), about 15% of the update (what running it once saved); for sarl, rgl and dsrnn the per-slot
work on 75 padded slots of which about 20 are observed. Adam, Polyak and Python overheads are
together under 5 ms. Batch 256 instead of 100 costs 2.3-2.6x per update (per sample 5-15% less):
the update is bound by arithmetic on the data, not by per-call overheads. ``--pseudo-vmap``
(the twin critics as two plain calls) gains only for lstm_rl (nn.LSTM's kernel); ``torch.compile``
was slower than eager: the gatedgcn actor's forward + backward 6.6 -> 7.8 ms after 34 s of
compilation (rgl 21 -> 29 ms), the vmapped critics no faster (graph breaks).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import statistics
import time

import torch

ENCODERS = "gatedgcn,sarl,lstm_rl,rgl,gat,dsrnn"


def make_learner(enc: str, overrides: list[str], frames: int, pseudo_vmap: bool = False, compact: bool = False):
    from omegaconf import open_dict
    from torchrl.collectors import Collector

    from crowdbench.algos.multiagent import agent_transitions
    from crowdbench.algos.registry import component
    from crowdbench.cli import compose
    from crowdbench.envs.factory import make_env

    cfg = compose([f"encoder={enc}", *overrides])
    if compact:
        from crowdbench.models.compact import COMPACTABLE

        if enc in COMPACTABLE:  # not a config key (yet): passed to make_encoder directly
            with open_dict(cfg):
                cfg.encoder.compact = True
    torch.manual_seed(0)
    env = make_env(cfg)
    learner = component(cfg.algo.name)(cfg, env.n_agents)
    if pseudo_vmap:  # what TD3Loss(deactivate_vmap=True) would do: the critic copies one after the other
        learner.loss.deactivate_vmap = True
        learner.loss._make_vmap()
    rb, policy = learner.rb, learner.collection_policy()
    for batch in Collector(env, policy, frames_per_batch=min(1024, frames), total_frames=frames,
                           auto_register_policy_transforms=False):
        rb.extend(agent_transitions(learner.store_base(batch), learner.keep))  # as OffPolicyAlgorithm.learn
    return learner, rb, cfg


def step_fn(learner, rb):
    def step(n: int):
        """Update ``n``: critic-only unless ``n`` is a multiple of policy_delay (then actor + targets too)."""
        sample = rb.sample()
        learner.update(sample, n)
        rb.update_tensordict_priority(sample)  # what train.py does (a no-op for uniform replay)
    return step


def time_round(step, reps: int) -> float:
    """Median ms per update over ``reps`` pairs (critic-only step, full step)."""
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        step(1)
        step(0)
        ts.append((time.perf_counter() - t) * 500)
    return statistics.median(ts)


def phases(learner, step, reps: int) -> dict[str, float]:
    """ms per update spent in each phase of ``OffPolicyAlgorithm.update`` (wrapped from outside, so that the
    learner runs unchanged): graph preparation, the critic term's forward, backward and Adam step,
    the actor term's, the Polyak update; "other" is the rest (sampling, priorities, Python)."""
    import crowdbench.algos.offpolicy as lmod

    acc: dict[str, float] = {}
    current = ["critic"]

    def timed(name, fn):
        def run(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                acc[name] = acc.get(name, 0.0) + time.perf_counter() - t
        return run

    def term(name, fn):
        def run(*a, **k):
            current[0] = name
            return timed(f"{name} forward", fn)(*a, **k)
        return run

    backward = torch.Tensor.backward
    saved = (lmod.prepare_batch, learner.critic_loss, learner.actor_loss, learner.opt_critic.step,
             learner.opt_actor.step, learner.target_updater.step)
    lmod.prepare_batch = timed("prepare_batch (graphs)", lmod.prepare_batch)
    learner.critic_loss = term("critic", learner.critic_loss)
    learner.actor_loss = term("actor", learner.actor_loss)
    learner.opt_critic.step = timed("critic Adam step", learner.opt_critic.step)
    learner.opt_actor.step = timed("actor Adam step", learner.opt_actor.step)
    learner.target_updater.step = timed("Polyak update", learner.target_updater.step)
    torch.Tensor.backward = lambda self, *a, **k: timed(f"{current[0]} backward", backward)(self, *a, **k)
    try:
        t = time.perf_counter()
        for _ in range(reps):
            step(1), step(0)
        total = time.perf_counter() - t
    finally:
        torch.Tensor.backward = backward
        lmod.prepare_batch, learner.critic_loss, learner.actor_loss = saved[:3]
        learner.opt_critic.step, learner.opt_actor.step, learner.target_updater.step = saved[3:]
    acc["other"] = total - sum(acc.values())
    return {k: 1000 * v / (2 * reps) for k, v in acc.items()}


def profile(step, enc: str, top: int) -> None:
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as tprofile

    for _ in range(3):
        step(1), step(0)
    with tprofile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(5):
            step(1), step(0)
    print(f"\n### {enc}: torch.profiler, 5 x (critic-only + full step), self CPU time")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=top, max_name_column_width=48))
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(5):
        step(1), step(0)
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("cumulative").print_stats(top)
    print(f"### {enc}: cProfile, 5 x (critic-only + full step), by cumulative time")
    print("\n".join(line for line in s.getvalue().splitlines() if line.strip()))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=15, help="update pairs per round")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--frames", type=int, default=2048, help="transitions collected into the buffer")
    ap.add_argument("--encoders", default=ENCODERS)
    ap.add_argument("--overrides", default="", help="training overrides, e.g. 'algo.batch_size=256'")
    ap.add_argument("--compact", action="store_true", help="sarl, rgl, dsrnn: the opt-in compacted human slots "
                    "(models/compact.py)")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--pseudo-vmap", action="store_true", help="TD3Loss's deactivate_vmap=True (an option for "
                    "algos/td3.py, not the shipped recipe): the two critics as two plain calls")
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args(argv)
    from crowdbench.models.perf import tune_allocator

    torch.set_num_threads(args.threads)
    tune_allocator()
    overrides = args.overrides.split()
    encoders = args.encoders.split(",")
    setups = {}
    for enc in encoders:
        learner, rb, cfg = make_learner(enc, overrides, args.frames, args.pseudo_vmap, args.compact)
        step = step_fn(learner, rb)
        for _ in range(5):  # warm-up (first calls allocate, build caches, compile)
            step(1), step(0)
        setups[enc] = (step, cfg.algo.batch_size, learner)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}" + (f"; {' '.join(overrides)}" if overrides else "")
          + ("; pseudo-vmap critics" if args.pseudo_vmap else "") + ("; compacted humans" if args.compact else ""))
    rounds = {enc: [] for enc in encoders}
    for _ in range(args.rounds):
        for enc in encoders:
            rounds[enc].append(time_round(setups[enc][0], args.reps))
    print(f"\n## ms per update (median of {args.rounds} round medians of {args.reps} update pairs)")
    print(f"  {'encoder':10s}{'ms/update':>11s}{'us/sample':>11s}{'updates/s':>11s}   rounds")
    for enc in encoders:
        ms, b = statistics.median(rounds[enc]), setups[enc][1]
        print(f"  {enc:10s}{ms:11.2f}{1000 * ms / b:11.1f}{1000 / ms:11.1f}   "
              + " ".join(f"{r:.1f}" for r in rounds[enc]))
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print("\n## where an update's time goes (ms per update, mean over the policy delay; one run of "
          f"{args.reps} update pairs)")
    table = {enc: phases(setups[enc][2], setups[enc][0], args.reps) for enc in encoders}
    names = list(dict.fromkeys(k for t in table.values() for k in t))
    print(f"  {'phase':24s}" + "".join(f"{enc:>10s}" for enc in encoders))
    for k in names:
        print(f"  {k:24s}" + "".join(f"{table[enc].get(k, 0.0):10.2f}" for enc in encoders))
    print(f"  {'total':24s}" + "".join(f"{sum(table[enc].values()):10.2f}" for enc in encoders))
    if args.profile:
        for enc in encoders:
            profile(setups[enc][0], enc, args.top)


if __name__ == "__main__":
    main()
