"""``crowdbench run``'s one run: train per the composed config, then evaluate on its protocol (also each
run of a sweep, crowdbench/sweep.py)."""

from __future__ import annotations

from pathlib import Path

from crowdbench.app import (
    Interrupted,
    UsageError,
    check_config,
    check_protocol,
    check_viz,
    claimed_output,
    eval_options,
    make_probe,
    output_dir,
    run_protocol,
)

# What the default recipe gives (docs/training.md, 3 seeds, pinned evaluation), printed when a run changes
# nothing of it: only where and how it runs (seed, output, threads, resuming, logging, evaluation, recordings).
DEFAULT_RECIPE = ("algo=td3", "encoder=gatedgcn")
RUN_ONLY = ("seed=", "out=", "cpus=", "resume=", "train.logger=", "train.save_buffer=", "eval.", "viz.")
EXPECTATION = ("the default recipe (a residual on ORCA): 11-12.5 minutes of training with cpus=2 on an idle 2-core machine "
               "(15 with cpus=1), more beside another run; expect about 0.958 average success on protocol v1's paper scenes (3 seeds: "
               "0.955-0.961; ORCA 0.935; exploration sigma 0.3, the previous default: 0.946; docs/training.md)")


def is_default_recipe(overrides: list[str]) -> bool:
    """Whether ``overrides`` leave the training recipe as the defaults compose it."""
    return all(o in DEFAULT_RECIPE or o.startswith(RUN_ONLY) for o in overrides)


def run_one(cfg, overrides: list[str]) -> dict:
    """One training run of ``cfg`` into ``cfg.out`` (or a new ``outputs/run-...``), then its evaluation."""
    import torch

    from crowdbench.algos.checkpoint import policy_from_checkpoint
    from crowdbench.algos.train import train

    check_config(cfg)  # also each run of a sweep (crowdbench/sweep.py task); cpus >= 1 included
    torch.set_num_threads(cfg.cpus)
    eval_options(cfg)
    check_viz(cfg)
    if cfg.resume and not cfg.out:
        raise UsageError("resume=true needs out=<run directory> (the run to continue)")
    if cfg.algo.name == "value":  # value-based lookahead: its own loop and policy (crowdbench/cli_value.py)
        from crowdbench.cli_value import run_value

        out = output_dir(cfg, "run", f"value-{cfg.algo.net}-{cfg.algo.lookahead}")
        with claimed_output(out):
            try:
                return run_value(cfg, out, overrides, resume=bool(cfg.resume))
            except ValueError as e:
                raise UsageError(str(e)) from None
            except KeyboardInterrupt:  # deep V-learning wrote its snapshot (algos/value_train.py RESUME_FILE)
                if not (out / "resume.pt").is_file():
                    raise Interrupted(f"interrupted during the imitation phase; nothing to resume in {out}") from None
                raise Interrupted(f"interrupted; resume with: {resume_command(overrides, out)}") from None
    check_protocol(cfg)  # e.g. self-play settings that cannot be placed: refused now, not after training
    out = output_dir(cfg, "run", f"{cfg.algo.name}-{cfg.encoder.name}")
    try:
        probe = make_probe(cfg)
    except ValueError as e:
        raise UsageError(str(e)) from None
    if is_default_recipe(overrides):
        print(EXPECTATION)
    with claimed_output(out):  # locked until the final evaluation is written; removed if nothing started
        try:
            stats = train(cfg, out, resume=bool(cfg.resume), probe=probe)
            if stats.get("interrupted"):
                raise Interrupted(f"interrupted at {stats['frames']:,} frames, checkpoint {out / 'checkpoint.pt'}; "
                                  f"resume with: {resume_command(overrides, out)}")
            print(f"trained {stats['frames']} frames, {stats['updates']} updates; checkpoint {out / 'checkpoint.pt'}")
            policy = policy_from_checkpoint(out / "checkpoint.pt")
        except ValueError as e:  # CheckpointError included: bad checkpoint, bad algo/replay/logger value
            raise UsageError(str(e)) from None
        # not strict: trained with other env.reactive values, evaluated on protocol v2's (the probe too)
        return run_protocol(policy, cfg, out, overrides, strict=False)


def resume_command(overrides: list[str], out: Path) -> str:
    """The command line that continues the run in ``out`` (the same overrides, ``out=``, ``resume=true``)."""
    import shlex

    keep = [o for o in overrides if not o.startswith(("out=", "resume=", "-m", "--multirun"))]
    return shlex.join(["crowdbench", "run", *keep, f"out={out}", "resume=true"])
