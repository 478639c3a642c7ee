"""The training loop, the same for every registered algorithm, readable top to bottom.

A TorchRL ``Collector`` steps ``B`` environments at once with the algorithm's collection policy
(after its random warm-up, if any); each collected ``[B, T]`` batch goes to the algorithm's
``learn`` (crowdbench/algos/base.py: a replay buffer and ``utd * frames`` updates for TD3 / DDPG /
SAC, epochs of clipped-objective minibatches for PPO); the loop logs, probes the held-out
scenes, checkpoints, and resumes from a checkpoint as if it had never stopped.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.collectors import Collector
from torchrl.envs import InitTracker, RewardSum
from tqdm import tqdm

from crowdbench.algos.base import Algorithm
from crowdbench.algos.checkpoint import FORMAT, CheckpointError, load_checkpoint
from crowdbench.algos.curriculum import CurriculumError, stage_of, stages, with_agents
from crowdbench.algos.loggers import close_logger, make_logger
from crowdbench.algos.multiagent import finished_episodes
from crowdbench.algos.registry import component
from crowdbench.algos.resume import check_resumable, truncate_log
from crowdbench.envs.factory import make_env
from crowdbench.envs.observation import GROUP
from crowdbench.envs.rules import COLLISION, SUCCESS
from crowdbench.models.perf import tune_allocator
from crowdbench.outputs import claim_dir, save_torch_atomic

EPISODE_RETURN = (GROUP, "episode_reward")
# keys a resumed run may change: the replay kind (and whether the losses correct for its sampling), e.g.
# continue a prioritized run with uniform replay; the saved transitions move into the new buffer (docs/training.md)
RESUME_FREE = {"algo": ("replay", "per_alpha", "per_beta", "per_weights")}
MODEL_KEYS = ("algo", "encoder", "env")


class DurationEstimate:
    """Prints the run's budget, then, after the second batch with updates, its expected duration:
    measured seconds per collected frame and per update x what remains of each; :meth:`remaining_s` gives
    the same estimate for the progress bar at every batch. The random warm-up is not timed: it acts ~15x
    faster than the policy, and a rate that includes it promises an early end. Timing only: no RNG."""

    def __init__(self, frames: int, updates: int, write):
        self.frames, self.write, self.updates = frames, write, updates
        self.frame_s = self.update_s = 0.0
        self.seen = self.n_frames = self.n_updates = self.update_batches = 0
        self.t = time.perf_counter()
        write(f"budget: {frames:,} frames, ~{self.updates:,} updates (the expected duration follows the first updates)")

    def collected(self, n: int) -> None:
        now = time.perf_counter()
        if self.update_batches:  # warm-up acts at random, faster than the policy: not timed
            self.frame_s += now - self.t
            self.n_frames += n
        self.seen += n
        self.t = now

    def updated(self, n: int) -> None:
        now = time.perf_counter()
        self.update_s += now - self.t
        self.n_updates += n
        self.update_batches += 1
        self.t = now
        if self.update_batches == 2:  # once; the first batch pays one-off allocations
            per_frame, per_update = self.frame_s / self.n_frames, self.update_s / self.n_updates
            self.write(f"expected duration: ~{self.remaining_s() / 60:.0f} min more ({1 / per_frame:,.0f} frames/s "
                       f"collecting, {1 / per_update:,.1f} updates/s on {torch.get_num_threads()} thread(s)), "
                       "plus the final evaluation")

    def remaining_s(self) -> float | None:
        """Seconds of training left at the measured post-warm-up rates; None before they are measured."""
        if self.update_batches < 2 or not self.n_frames:
            return None
        per_frame, per_update = self.frame_s / self.n_frames, self.update_s / self.n_updates
        return (self.frames - self.seen) * per_frame + max(0, self.updates - self.n_updates) * per_update

    def postfix(self) -> str:
        left = self.remaining_s()
        return "warm-up" if left is None else tqdm.format_interval(left)

    def lap(self) -> None:
        self.collected(0)


class StopRequest:
    """Ctrl-C (SIGINT) during training asks the loop to stop after the current batch and checkpoint there,
    so that ``resume=true`` continues exactly; a second Ctrl-C stops at once (no checkpoint). Outside the
    main thread (e.g. a Ray task) signals cannot be caught and the default applies."""

    def __init__(self, write):
        self.write, self.requested, self.previous = write, False, None

    def install(self) -> StopRequest:
        try:
            self.previous = signal.signal(signal.SIGINT, self._handle)
        except ValueError:  # not the main thread
            self.previous = None
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        self.write("Ctrl-C: stopping after this batch with a checkpoint (Ctrl-C again: stop now, without one)")

    def restore(self) -> None:
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)


def check_budget(t: DictConfig) -> None:
    total = t.total_frames
    if isinstance(total, bool) or not isinstance(total, int) or total < 1:
        raise ValueError(f"train.total_frames must be a positive integer, got {total!r}")


def load_resume_state(cfg: DictConfig, ckpt_path: Path, fields: tuple[str, ...]) -> dict:
    """The checkpoint to continue, checked: a training checkpoint (``fields`` and the loop's own) whose
    model and task are ``cfg``'s."""
    state = load_checkpoint(ckpt_path)
    check_resumable(state, ckpt_path, fields)
    saved = OmegaConf.create(state["config"])
    for key in MODEL_KEYS:  # the model and task must be the ones that were trained
        before, now = OmegaConf.to_container(saved[key]), OmegaConf.to_container(cfg[key])
        for free in RESUME_FREE.get(key, ()):
            before.pop(free, None)
            now.pop(free, None)
        if before != now:
            diff = sorted(k for k in before.keys() | now.keys() if before.get(k) != now.get(k))
            raise CheckpointError(f"resume: config '{key}' differs from the checkpoint's in {ckpt_path} "
                                  f"({', '.join(f'{key}.{k}' for k in diff)})")
    return state


def warm_start(cfg: DictConfig, env, algo: Algorithm, logger, write=None) -> dict[str, float]:
    """``train.pretrain``: demonstrations on the training env, then the algorithm's imitation warm start;
    its scalars are logged at frame 0 (``crowdbench/algos/pretrain.py``)."""
    from crowdbench.algos.pretrain import collect_demonstrations, dagger, expert_policy

    t = cfg.train
    if type(algo).warm_start is Algorithm.warm_start:
        raise ValueError(f"train.pretrain={t.pretrain}: algo={algo.name} has no imitation warm start")
    start = time.perf_counter()
    expert = expert_policy(cfg, env)
    demos = collect_demonstrations(cfg, env, t.pretrain_frames, expert)
    collected = time.perf_counter()
    logs = algo.warm_start(demos)
    if int(t.get("pretrain_dagger_rounds", 0)) > 0:
        data, more = dagger(cfg, env, algo.actor, algo.actor_kind, expert, demos)
        algo.clone_from(data)
        logs.update(more)
    logs["pretrain_collect_s"] = collected - start
    logs["pretrain_fit_s"] = time.perf_counter() - collected
    for k, v in logs.items():
        logger.log_scalar(k, v, step=0)
    if write is not None:
        took = logs["pretrain_collect_s"] + logs["pretrain_fit_s"]
        write(f"warm start ({t.pretrain}, {len(demos):,} transitions, {took:.0f} s): held-out action MSE "
              f"{logs['pretrain_heldout_action_mse_before']:.4f} -> {logs['pretrain_heldout_action_mse']:.4f}")
        rounds = [logs[k] for k in sorted(logs) if k.startswith("dagger_") and k.endswith("_student_success")]
        if rounds:
            write(f"DAgger ({len(rounds)} rounds, {logs['dagger_transitions']:,.0f} labelled transitions): the "
                  f"student's success per round {', '.join(f'{x:.2f}' for x in rounds)}")
    return logs


def train(cfg: DictConfig, out_dir: Path, resume: bool = False, progress: bool = True, probe=None) -> dict:
    """Train per ``cfg`` into ``out_dir`` (``checkpoint.pt``, ``replay-*/``, ``logs/``); return final stats.

    ``probe(actor) -> dict[str, float]``, if given, is called every ``train.probe_every`` frames
    and its scalars are logged (the CLI passes a held-out evaluation; algos do not import eval).
    Training stops at ``train.total_frames`` or after ``train.max_minutes`` of wall time.
    ``out_dir`` is locked for the run (a second concurrent run into it fails at once); a run that fails
    before it starts leaves no directory behind.
    """
    out_dir = Path(out_dir)
    check_budget(cfg.train)
    with claim_dir(out_dir):
        return _train(cfg, out_dir, resume, progress, probe)


def _train(cfg: DictConfig, out_dir: Path, resume: bool, progress: bool, probe) -> dict:
    ckpt_path = out_dir / "checkpoint.pt"
    state = None
    if not resume and ckpt_path.exists():  # a fresh run would overwrite it and append to its logs
        raise CheckpointError(f"{out_dir} already holds a training run ({ckpt_path.name}); "
                              "pass resume=true to continue it, or choose another out=")
    Algo = component(cfg.algo.name)
    if resume:
        state = load_resume_state(cfg, ckpt_path, Algo.resume_fields)
    t = cfg.train
    plan = stages(cfg)  # [(n_agents, end frames)]: one stage unless train.curriculum_agents is set
    if len(plan) > 1 and Algo.replays:
        raise CurriculumError(f"train.curriculum_agents needs an on-policy algorithm (ppo, ippo, mappo): algo="
                              f"{cfg.algo.name}'s replay buffer holds one agent count's observations")
    tune_allocator()
    torch.manual_seed(cfg.seed)

    def make(n_agents: int):
        # replay (one robot) or self-play (n agents, one shared-weight policy); progress shaping for training only
        # InitTracker: the OU noise restarts from zero in every new episode
        c = with_agents(cfg, n_agents) if "n_agents" in cfg.env else cfg
        return make_env(c, progress_reward=t.progress_reward, human_dropout=t.human_dropout,
                        human_thinning=t.get("human_thinning", 0.0),
                        playback_speeds=t.get("playback_speeds", (1.0,)),
                        extra=(InitTracker(), RewardSum(in_keys=[(GROUP, "reward")], out_keys=[EPISODE_RETURN]),
                               *Algo.env_transforms(c)))

    stage = stage_of(plan, int(state["frames"]) if state is not None else 0)
    env = make(plan[stage][0])
    algo = Algo(cfg, env.n_agents)
    # window: (outcome, return) of recently finished episodes
    start = {"frames": 0, "window": [], "restored": False, "last_probe": 0, "plan": plan, "stage": stage, "make": make}
    if state is not None:
        algo.load_state_dict(state)
        if state.get("stage", stage) == stage:  # (saved at a stage's end: the next stage's env starts afresh)
            env.sampler.load_state_dict(state["sampler"])
        torch.set_rng_state(state["torch_rng"])
        frames = start["frames"] = int(state["frames"])
        algo.updates = int(state["updates"])
        start["restored"] = algo.restore_extra(state, ckpt_path)
        start["window"] = list(zip(*state["window"], strict=True)) if "window" in state else []
        start["last_probe"] = int(state.get("last_probe", frames))
        truncate_log(out_dir / "logs", frames)

    logger = make_logger(t.logger, out_dir, cfg, print if progress else lambda _: None)
    failed = True
    try:
        stats = _loop(cfg, out_dir, env, algo, logger, state, start, progress, probe)
        failed = False
        return stats
    finally:
        close_logger(logger, failed)


def _loop(cfg, out_dir, env, algo, logger, state, start: dict, progress, probe) -> dict:
    """The warm start (a fresh run's, if any) and the collect-learn-log-checkpoint loop from ``start``."""
    t, actor, ckpt_path = cfg.train, algo.actor, out_dir / "checkpoint.pt"
    frames, window, last_probe, restored = start["frames"], start["window"], start["last_probe"], start["restored"]
    warm_s = 0.0  # the warm start's wall time, counted in max_minutes with train.budget_warm_start
    if state is None and t.get("pretrain"):
        logs = warm_start(cfg, env, algo, logger, print if progress else None)
        warm_s = logs["pretrain_collect_s"] + logs["pretrain_fit_s"] if t.get("budget_warm_start") else 0.0
    remaining = t.total_frames - frames
    if remaining <= 0:
        return {"frames": frames, "updates": algo.updates}
    plan, make, current = start["plan"], start["make"], {"env": env, "stage": start["stage"]}

    def batches():
        """The collected batches of each remaining stage (train.curriculum_agents): a stage's own env and collector."""
        first = True
        for i in range(current["stage"], len(plan)):
            n, end = plan[i]
            if i != current["stage"]:  # a fresh env (its sampler from the seed), as a resumed run builds it
                current["env"].close()
                current["env"], current["stage"] = make(n), i
                algo.n_agents = n
            collector = Collector(
                current["env"], algo.collection_policy(), frames_per_batch=t.frames_per_batch,
                total_frames=end - frames,
                init_random_frames=algo.random_frames(state is not None, restored, frames) if first else 0,
                auto_register_policy_transforms=False,
            )
            first = False
            try:
                yield from collector
            finally:
                collector.shutdown()

    def save(wall_time_s: float):
        try:  # what the checkpoint references first (the replay buffer), then the checkpoint, then cleanup
            extra = algo.save_extra(out_dir, frames)
            save_torch_atomic(ckpt_path, {
                "config": OmegaConf.to_container(cfg, resolve=True), **algo.state_dict(), **extra,
                "sampler": current["env"].sampler.state_dict(), "stage": current["stage"], "torch_rng": torch.get_rng_state(),
                "frames": frames, "updates": algo.updates, "wall_time_s": wall_time_s, "last_probe": last_probe,
                "window": [[o for o, _ in window], [r for _, r in window]], "format": FORMAT,
            })
        except OSError as e:
            kept = f"; the previous checkpoint is kept ({ckpt_path})" if ckpt_path.exists() else ""
            raise CheckpointError(f"cannot write the checkpoint in {out_dir}: "
                                  f"{e.strerror or e} ({e.filename or ckpt_path}){kept}") from None
        algo.after_save(out_dir, extra)

    # tqdm's own remaining time would come from a rate that includes the warm-up: the estimate's instead
    bar = tqdm(total=t.total_frames, initial=frames, disable=not progress, unit="frame", dynamic_ncols=True,
               bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]")  # postfix: ", eta ..."
    stop = StopRequest(bar.write if progress else print).install()  # before the budget line: Ctrl-C is safe
    # a resumed run refills warm-up frames too
    eta = DurationEstimate(remaining, algo.expected_updates(remaining), bar.write)
    last_ckpt, start = frames, time.time()
    elapsed0 = float(state["wall_time_s"]) if state is not None else warm_s
    stats: dict = {}
    collected = batches()
    try:
        for batch in collected:
            eta.collected(batch.numel())
            frames += batch.numel()
            outcome, ret = finished_episodes(batch, EPISODE_RETURN)  # per agent episode
            window = (window + list(zip(outcome, ret, strict=True)))[-t.stats_window:]
            before = algo.updates
            logs = algo.learn(batch)
            if algo.updates > before:
                eta.updated(algo.updates - before)
            if window:
                stats = {
                    "success_rate": sum(o == SUCCESS for o, _ in window) / len(window),
                    "collision_rate": sum(o == COLLISION for o, _ in window) / len(window),
                    "episode_return": sum(r for _, r in window) / len(window),
                }
                logs.update(stats)
            logs["updates"] = algo.updates
            if t.get("curriculum_agents"):  # the agent curriculum's stage
                logs["agents"] = algo.n_agents
            logs["wall_time_s"] = wall = elapsed0 + time.time() - start
            if probe is not None and frames - last_probe >= t.probe_every:
                logs.update(probe(actor))
                last_probe = frames
            eta.lap()  # probes and checkpoints count as part of the next batch's collection time
            for k, v in logs.items():
                logger.log_scalar(k, v, step=frames)
            bar.update(batch.numel())
            bar.set_postfix_str(", ".join([f"eta {eta.postfix()}", *(f"{k}={v:.2f}" for k, v in stats.items()),
                                           f"upd={algo.updates}"]))
            if frames - last_ckpt >= t.checkpoint_every:
                save(wall)
                last_ckpt = frames
            if (t.max_minutes and wall >= 60 * t.max_minutes) or stop.requested:
                break
        save(wall)
    except OSError as e:  # e.g. the logs' directory made read-only: one line, the last checkpoint stays
        kept = f"; the last checkpoint ({ckpt_path}) is kept" if ckpt_path.exists() else "; no checkpoint was written"
        raise CheckpointError(f"cannot write {e.filename or out_dir}: {e.strerror or e}{kept}") from None
    finally:
        stop.restore()
        bar.close()
        collected.close()
    return {"frames": frames, "updates": algo.updates, **stats, **({"interrupted": True} if stop.requested else {})}
