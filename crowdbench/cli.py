"""``crowdbench`` command line: Hydra-composed configs, one-line errors for bad input."""

from __future__ import annotations

import sys
from pathlib import Path

from crowdbench import policies
from crowdbench.app import (  # the evaluation half of the command line
    Interrupted,
    UsageError,
    check_config,
    check_protocol,
    check_viz,
    eval_output,
    make_policy,
    run_protocol,
)
from crowdbench.cli_run import run_one
from crowdbench.cli_submit import cmd_submit
from crowdbench.compose import CONFIG_DIR, compose, hydra_message, normalise  # noqa: F401 - re-exported

COMMANDS = ("eval", "run", "leaderboard", "submit", "viz", "plot")
BASELINES = policies.NAMES  # the registry's built-in policies


def cmd_eval(overrides: list[str]) -> int:
    from crowdbench.envs.rules import check_seed

    cfg = compose(overrides)
    check_config(cfg)
    try:
        check_seed(cfg.seed)
    except ValueError as e:
        raise UsageError(str(e)) from None
    protocol = check_protocol(cfg, str(cfg.policy))  # bad scenes, fixed settings, policies before loading anything
    if protocol.per_scene:
        check_viz(cfg)  # the recordings are of scenes' episodes
    with eval_output(cfg, protocol.command) as out:
        run_protocol(make_policy(str(cfg.policy), cfg), cfg, out, overrides)
    return 0


def cmd_run(overrides: list[str]) -> int:
    """Train on the training scene, checkpoint periodically, then evaluate on the protocol; with
    ``-m`` / ``--multirun``, a Hydra sweep of such runs (crowdbench/sweep.py)."""
    if {"-m", "--multirun"} & set(overrides):
        from crowdbench.sweep import multirun

        return multirun([o for o in overrides if o not in ("-m", "--multirun")])
    run_one(compose(overrides), overrides)
    return 0


def cmd_leaderboard(args: list[str]) -> int:
    """Validate and evaluate leaderboard submissions, regenerate the tables (docs/submitting.md section 4)."""
    import argparse

    from crowdbench.data.scenes import check_scene
    from crowdbench.envs.protocol import EVAL_SCENES
    from crowdbench.leaderboard import BLOCK_START, DEFAULT_ROOT, LAUNCHERS, run
    from crowdbench.leaderboard.render import blocks_in
    from crowdbench.leaderboard.sandbox import SANDBOXES, Limits
    from crowdbench.leaderboard.tracks import TRACK_ORDER, check_tracks

    ap = argparse.ArgumentParser(prog="crowdbench leaderboard",
                                 description="Validate and evaluate leaderboard submissions; regenerate the table.")
    ap.add_argument("--check", action="store_true", help="re-evaluate everything (no cache, nothing written; "
                    "with --only: those submissions, the others as committed); "
                    "exit 1 if leaderboard/README.md or a generated block (README, docs) differs from the fresh result")
    ap.add_argument("--force", action="store_true", help="re-evaluate even unchanged submissions")
    ap.add_argument("--only", action="append", metavar="NAME", help="evaluate only this submission (repeatable, "
                    "or comma-separated); "
                    "the others keep their cached results (with --check: their committed ones)")
    ap.add_argument("--episodes", type=int, default=None, help="N episodes per scene (evenly strided; unofficial)")
    ap.add_argument("--scenes", default=None, help="comma-separated scene subset (unofficial)")
    ap.add_argument("--jobs", type=int, default=1, help="evaluate N submissions in parallel "
                    "(each single-threaded; the numbers do not depend on N)")
    ap.add_argument("--launcher", choices=LAUNCHERS, default="local", help="local: a process pool of --jobs; "
                    "ray: one Ray task per submission (a local cluster of --jobs CPUs, or --address)")
    ap.add_argument("--address", default=None, help="--launcher ray: join this cluster (auto, ray://host:10001)")
    ap.add_argument("--tracks", default=None, help="comma-separated tracks to evaluate (default all: "
                    + ", ".join(TRACK_ORDER) + "); the others keep their cached results")
    ap.add_argument("--root", type=Path, default=None, help=f"leaderboard directory (default {DEFAULT_ROOT})")
    ap.add_argument("--sandbox", choices=SANDBOXES, default="auto", help="confine learned submissions' worker "
                    "processes with bubblewrap (auto: where bwrap works; none: resource limits only)")
    ap.add_argument("--worker-timeout", type=float, default=Limits.step_s, metavar="SECONDS",
                    help=f"a worker's longest answer to one observation batch (default {Limits.step_s:g})")
    ap.add_argument("--worker-load-timeout", type=float, default=Limits.load_s, metavar="SECONDS",
                    help=f"a worker's longest start (importing the code, loading the checkpoint; default {Limits.load_s:g})")
    ap.add_argument("--budget-factor", type=float, default=Limits.budget_factor, metavar="X",
                    help="a learned submission's wall-clock budget per track: X times ORCA's time on the same "
                         f"track (default {Limits.budget_factor:g}; at least {Limits.budget_floor_s:g} s)")
    ap.add_argument("--worker-memory", type=float, default=Limits.memory_gb, metavar="GB",
                    help=f"a worker's address-space limit (default {Limits.memory_gb:g})")
    ap.add_argument("--readme", type=Path, default=None, help="also regenerate the results block of this file "
                    "(default: ./README.md when --root is not given and it has the block)")
    ap.add_argument("--docs", type=Path, action="append", default=None, metavar="FILE",
                    help="also regenerate the generated blocks of this file (repeatable; default: "
                    "docs/results.md and docs/reproduction.md when --root is not given and they have them)")
    ap.add_argument("--site", type=Path, default=None, metavar="DIR", help="also write the leaderboard as a "
                    "static web site into DIR (from the results on disk; docs/submitting.md section 4)")
    ap.add_argument("--site-figures", type=int, default=2, metavar="N", help="--site: N episodes per entry for "
                    "its trajectory figure and rerun recordings (cached; 0: none; default 2)")
    a = ap.parse_args(args)
    if a.episodes is not None and a.episodes < 1:
        ap.error("--episodes must be >= 1")
    if a.site is not None and a.check:
        ap.error("--site writes files; --check writes nothing: run them separately")
    if not 0 <= a.site_figures <= 50:
        ap.error("--site-figures must be in [0, 50]")
    scenes = None
    if a.scenes:
        try:
            scenes = [check_scene(s.strip()) for s in a.scenes.split(",") if s.strip()]
        except ValueError as e:
            ap.error(str(e))
        bad = [s for s in scenes if s not in EVAL_SCENES]
        if bad:
            ap.error(f"not an evaluation scene: {', '.join(bad)}; valid: {', '.join(EVAL_SCENES)}")
    if a.jobs < 1:
        ap.error("--jobs must be >= 1")
    if not (0 < a.worker_timeout < 86400):
        ap.error("--worker-timeout must be in (0, 86400) seconds")
    if not (1 <= a.worker_memory <= 1024):
        ap.error("--worker-memory must be in [1, 1024] GB")
    if not (0 < a.worker_load_timeout < 86400):
        ap.error("--worker-load-timeout must be in (0, 86400) seconds")
    if not (1 <= a.budget_factor <= 10000):  # (also refuses nan)
        ap.error("--budget-factor must be in [1, 10000]")
    limits = Limits(step_s=a.worker_timeout, load_s=a.worker_load_timeout, memory_gb=a.worker_memory,
                    sandbox=a.sandbox, budget_factor=a.budget_factor)
    if a.address and a.launcher != "ray":
        ap.error("--address needs --launcher ray")
    readme = a.readme
    if readme is None and a.root is None:  # the repository's own run; a scratch --root never touches it
        default = Path("README.md")
        readme = default if default.is_file() and BLOCK_START in default.read_text() else None
    docs = a.docs
    if docs is None and a.root is None:
        docs = [p for p in (Path("docs/results.md"), Path("docs/reproduction.md"), Path("docs/training.md"))
                if p.is_file() and blocks_in(p.read_text())]
    tracks = None
    if a.tracks:
        try:
            tracks = check_tracks(t.strip() for t in a.tracks.split(",") if t.strip())
        except ValueError as e:
            ap.error(str(e))
    only = [n.strip() for o in a.only for n in o.split(",") if n.strip()] if a.only else None  # names have no commas
    try:
        return run(a.root or DEFAULT_ROOT, only, a.check, a.force, a.episodes, scenes, jobs=a.jobs,
                   launcher=a.launcher, address=a.address, readme=readme, docs=docs, tracks=tracks, limits=limits,
                   site=a.site, site_figures=a.site_figures, progress=True)
    except KeyboardInterrupt:  # the jobs and their workers are stopped; results written so far are kept
        print("crowdbench leaderboard: interrupted; results written so far are kept", file=sys.stderr)
        return 130


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        from crowdbench.cli_usage import usage

        print(usage())
        return 0
    if argv[0] in ("-V", "--version"):
        from crowdbench.cli_usage import version

        print(version())
        return 0
    command, overrides = argv[0], argv[1:]
    try:
        if command not in COMMANDS:
            raise UsageError(f"unknown command {command!r}; valid commands: {', '.join(COMMANDS)}")
        if command in ("run", "eval"):
            from crowdbench.cli_usage import hydra_flags, wants_hydra

            if wants_hydra(overrides):
                return hydra_flags(command, overrides)
        if command in ("viz", "plot"):
            from crowdbench.viz.commands import main as viz_main

            try:
                return viz_main(command, overrides)
            except ValueError as e:
                raise UsageError(str(e)) from None
        return {"eval": cmd_eval, "run": cmd_run, "leaderboard": cmd_leaderboard,
                "submit": cmd_submit}[command](overrides)
    except UsageError as e:
        print(f"crowdbench: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # Ctrl-C: one line (a run says how to resume), no traceback
        print(f"crowdbench: {e}" if isinstance(e, Interrupted) else "crowdbench: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
