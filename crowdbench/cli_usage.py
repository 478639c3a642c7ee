"""``crowdbench --help``, ``--version`` and Hydra's own flags for ``run`` and ``eval``.

The usage lists what the registries hold (algorithms, encoders, policies) and what the config groups
hold (envs, experiments, methods), so that a newly registered algorithm or encoder shows up without
editing this text.
"""

from __future__ import annotations

import sys
from pathlib import Path

CONFIG_DIR = Path(__file__).resolve().parent / "conf"
# Hydra's command-line flags: with one of them, run/eval hand the command line to Hydra (no training);
# --resolve and --package refine --cfg
HYDRA_FLAGS = ("-h", "--help", "--hydra-help", "-c", "--cfg", "-i", "--info")

COMMANDS = {  # command -> (its arguments, what it does)
    "run": ("[algo=ALGO] [encoder=ENCODER] [env=ENV] [key=value ...] [-m]",
            "train on the training scene, checkpoint, then evaluate on the protocol (-m: a Hydra sweep)"),
    "eval": ("[policy=POLICY|RUN/checkpoint.pt] [env=ENV] [key=value ...]",
             "evaluate a baseline or a checkpoint on a protocol (pinned numerics), write results.json"),
    "leaderboard": ("[--only NAME] [--tracks T,...] [--launcher local|ray] [--root DIR] ...",
                    "validate and evaluate leaderboard submissions, regenerate the tables"),
    "submit": ("RUN|SWEEP_DIR [--name NAME] [--entry LABEL] [--root DIR]",
               "a training run (or every finished run of a sweep) -> leaderboard/submissions/"),
    "viz": ("OUT|episodes.jsonl [--episode N] [--scene S] [--grid K] [--out FILE.png] [--video FILE.gif|.mp4]",
            "a figure or a video of recorded episodes"),
    "plot": ("RUN [RUN ...] [--out FILE.png] [--smooth N]", "training curves of runs (CSV or TensorBoard logs)"),
}


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    def v(dist: str) -> str:
        try:
            return dist_version(dist)
        except PackageNotFoundError:
            return "not installed"

    return f"crowdbench {v('crowdbench')} (torch {v('torch')}, torchrl {v('torchrl')}, Python {sys.version.split()[0]})"


def group(name: str) -> list[str]:
    """The options of config group ``name`` (``crowdbench/conf/<name>/*.yaml``)."""
    return sorted(p.stem for p in (CONFIG_DIR / name).glob("*.yaml"))


def usage() -> str:
    from crowdbench import policies
    from crowdbench.algos.registry import names as algo_names
    from crowdbench.leaderboard.tracks import TRACK_ORDER
    from crowdbench.models import ENCODERS

    privileged = [f"{n} (privileged)" if n in policies.PRIVILEGED else n for n in policies.NAMES]
    lines = ["usage: crowdbench <command> [arguments]      crowdbench <command> --help: the command's options",
             "       crowdbench --version", "", "commands:"]
    lines += [f"  {c:<12} {what}\n  {'':<12}   crowdbench {c} {args}" for c, (args, what) in COMMANDS.items()]
    lines += ["", "registered (run/eval overrides):",
              f"  algo=      {', '.join(algo_names())}",
              f"  encoder=   {', '.join(ENCODERS)}",
              f"  policy=    {', '.join(privileged)}, or a checkpoint path",
              f"  env=       {', '.join(group('env'))}",
              f"  method=    {', '.join(group('method'))}",
              f"  experiment= {', '.join(group('experiment'))}",
              f"  leaderboard tracks: {', '.join(TRACK_ORDER)}",
              "", "run/eval take Hydra overrides (key=value) and Hydra's flags: --help, --cfg job, --info.",
              "Guide: docs/guide.md; Python API: docs/api.md."]
    return "\n".join(lines)


def wants_hydra(overrides: list[str]) -> bool:
    return any(o in HYDRA_FLAGS or o.split("=", 1)[0] in ("--cfg", "--info") for o in overrides)


INFO_CHOICES = ("all", "config", "defaults", "defaults-tree", "plugins", "searchpath")


def overrides_only(args: list[str]) -> list[str]:
    """``args`` without Hydra's flags and their values (``--cfg job``, ``--info defaults``, ``-p PKG``)."""
    out, skip = [], False
    for i, a in enumerate(args):
        if skip:
            skip = False
            continue
        if a in ("-c", "--cfg", "-p", "--package"):
            skip = True
        elif a in ("-i", "--info"):
            skip = i + 1 < len(args) and args[i + 1] in INFO_CHOICES
        elif not a.startswith("-"):
            out.append(a)
    return out


def hydra_flags(command: str, overrides: list[str]) -> int:
    """``crowdbench run|eval --help / --cfg job / --info ...``: Hydra's answer for this command's config;
    nothing is trained or evaluated (Hydra prints and returns before calling the task)."""
    import hydra

    from crowdbench.app import UsageError
    from crowdbench.compose import compose, normalise

    args, what = COMMANDS[command]
    plain = overrides_only(overrides)
    if not {"-m", "--multirun"} & set(overrides):  # a sweep's "a,b" values are Hydra's to expand
        compose(plain)  # a bad key or option: the one-line UsageError, not Hydra's multi-line report
    if {"-h", "--help"} & set(overrides):
        print(f"crowdbench {command} {args}\n  {what}\n")

    def never(cfg) -> None:  # with these flags Hydra prints and returns before calling the task
        raise AssertionError("not reached")

    app = hydra.main(config_path=str(CONFIG_DIR), config_name="config", version_base="1.3")(never)
    argv, sys.argv = sys.argv, [f"crowdbench {command}", *normalise(overrides)]
    try:
        app()
    except SystemExit as e:  # Hydra exits on a bad override, after printing the error
        return int(e.code or 0) if not isinstance(e.code, str) else 2
    except ValueError as e:  # e.g. --cfg with -m: "Only one of --run, --multirun, --cfg, ..."
        raise UsageError(f"{command}: {' '.join(str(e).split())}") from None
    finally:
        sys.argv = argv
    return 0
