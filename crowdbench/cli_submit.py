"""``crowdbench submit``: a training run, or every finished run of a sweep, -> leaderboard submissions.

A sweep's runs are named and labelled from the sweep itself: the run's ``submission.*`` config (a method
or an experiment sets the row label), the overrides that differ between the sweep's runs (so that two
configurations never share a row), and a version suffix when a name or label is already on the
leaderboard (a re-submission never replaces or joins a row it did not make).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import yaml

from crowdbench.app import UsageError

# overrides already spelt by the run's name (method = encoder + algorithm) or that separate seeds of a row
NAMED_KEYS = ("seed", "method", "experiment", "encoder", "algo", "out", "hydra/launcher")


def parser() -> argparse.ArgumentParser:
    from crowdbench.leaderboard import DEFAULT_ROOT

    ap = argparse.ArgumentParser(prog="crowdbench submit",
                                 description="Make leaderboard/submissions/NAME from a run directory, or one "
                                             "submission per finished run of a sweep directory.")
    ap.add_argument("run", type=Path, help="run directory (holds checkpoint.pt) or sweep directory (multirun.yaml)")
    ap.add_argument("--name", default=None, help="submission name (a sweep: the prefix of every run's name; "
                    "default: the run's submission.name, e.g. gatedgcn_td3_s0)")
    ap.add_argument("--entry", default=None, help="row label; seeds of one method share it (default: the "
                    "run's submission.entry, set by method=...; a plain sweep: its method and varied overrides)")
    ap.add_argument("--authors", default="crowdbench", help="comma-separated author names")
    ap.add_argument("--link", default=None)
    ap.add_argument("--notes", default=None)
    ap.add_argument("--root", type=Path, default=None, help=f"leaderboard directory (default {DEFAULT_ROOT})")
    return ap


def cmd_submit(args: list[str]) -> int:
    """Turn a training run, or every finished run of a sweep, into leaderboard submissions (slim
    checkpoint + submission.yaml); print the ``crowdbench leaderboard`` command that evaluates them."""
    from crowdbench.leaderboard import DEFAULT_ROOT

    a = parser().parse_args(args)
    authors = [x.strip() for x in a.authors.split(",") if x.strip()]
    root = a.root or DEFAULT_ROOT
    if not (a.run / "multirun.yaml").is_file():
        path = submit_run(a.run, a.name, a.entry, authors, a.link, a.notes, root, None)
        print(f"wrote {path}; evaluate it with: {follow_up([path.name], a.root)}")
        return 0
    plan, problems = plan_sweep(a.run, a.name, a.entry, root)
    written = []
    for d, status, name, entry in plan:
        try:
            written.append(submit_run(d, name, entry, authors, a.link, a.notes, root, status["overrides"]))
            print(f"{d} -> {name} ({entry})")
        except UsageError as e:
            print(f"crowdbench: error: {e}", file=sys.stderr)
            problems += 1
    print(f"wrote {len(written)} submissions under {root / 'submissions'}" +
          (f"; evaluate them with: {follow_up([p.name for p in written], a.root)}" if written else ""))
    return 1 if problems else 0


def follow_up(names: list[str], root: Path | None) -> str:
    return "crowdbench leaderboard" + (f" --root {root}" if root is not None else "") + f" --only {','.join(names)}"


def finished_runs(sweep: Path) -> tuple[list[tuple[Path, dict]], list[list[str]], int]:
    """``([(run dir, status)] of the finished runs, every run's overrides, how many did not finish)``."""
    from crowdbench.sweep import STATUS

    runs = sorted((d for d in sweep.iterdir() if d.is_dir() and d.name.isdigit()), key=lambda d: int(d.name))
    if not runs:
        raise UsageError(f"submit: {sweep} holds no runs")
    done, every, problems = [], [], 0
    for d in runs:
        status = json.loads((d / STATUS).read_text()) if (d / STATUS).is_file() else {}
        every.append(status.get("overrides", []))
        if status.get("status") != "ok":
            print(f"crowdbench: run {d} did not finish ({status.get('error', 'no status.json')}): not submitted",
                  file=sys.stderr)
            problems += 1
            continue
        done.append((d, status))
    return done, every, problems


def varied(overrides: list[str], common: set[str]) -> list[str]:
    """The overrides of a run that not every run of its sweep has, except those its name already spells."""
    return [o for o in overrides if o not in common and o.split("=", 1)[0].lstrip("+~") not in NAMED_KEYS]


def slug(overrides: list[str]) -> str:
    """``encoder.dim=8 train.utd=0.5`` -> ``dim8_utd0.5``: a name part (the last key part and the value)."""
    parts = [o.split("=", 1)[0].rsplit(".", 1)[-1] + o.split("=", 1)[1] for o in overrides]
    return re.sub(r"[^A-Za-z0-9.-]+", "_", "_".join(parts)).strip("._-")[:40].strip("._-")


def plan_sweep(sweep: Path, prefix: str | None, entry: str | None, root: Path):
    """``[(run dir, status, name, label)]`` for the sweep's finished runs, and how many did not finish.

    Runs of one configuration (they differ in the seed only) share a label and a name stem; a stem or label
    already on the leaderboard, or taken by another configuration of this sweep, gets ``_v2``/``#2``, ..."""
    from crowdbench.algos.checkpoint import CheckpointError, load_checkpoint

    done, every, problems = finished_runs(sweep)
    common = set.intersection(*(set(o) for o in every)) if every else set()
    groups: dict[tuple[str, str], list] = {}
    for d, status in done:
        try:
            cfg = load_checkpoint(d / "checkpoint.pt")["config"]
        except CheckpointError as e:
            raise UsageError(f"submit: {e}") from None
        meta, var = cfg.get("submission") or {}, varied(status["overrides"], common)
        stem = prefix or re.sub(r"_?s\d+$", "", str(meta.get("name") or "")) or meta.get("method") or "run"
        label = entry or meta.get("entry") or f"{meta.get('method') or stem} ({sweep.resolve().name})"
        if var:  # another configuration of this sweep: its own name stem and row
            stem = f"{stem}_{slug(var)}"
            label = f"{label.removesuffix(')')}, {' '.join(var)})" if label.endswith(")") else f"{label} ({' '.join(var)})"
        members = groups.setdefault((stem, label), [])
        if any(seed == int(cfg["seed"]) for _, _, seed in members):
            raise UsageError(f"submit: runs {members[0][0]} and {d} have the same configuration and seed")
        members.append((d, status, int(cfg["seed"])))
    names, labels = existing(root)
    plan = []
    for (stem, label), members in groups.items():
        k = 1  # the first version whose names and label are free
        while {f"{stem}{_v(k)}_s{s}" for _, _, s in members} & names or label + _mark(k) in labels:
            k += 1
        names |= {f"{stem}{_v(k)}_s{s}" for _, _, s in members}
        labels.add(label + _mark(k))
        plan += [(d, status, f"{stem}{_v(k)}_s{s}", label + _mark(k)) for d, status, s in members]
    return sorted(plan, key=lambda p: int(p[0].name)), problems


def _v(k: int) -> str:
    return "" if k == 1 else f"_v{k}"


def _mark(k: int) -> str:
    return "" if k == 1 else f" #{k}"


def existing(root: Path) -> tuple[set[str], set[str]]:
    """The submission names and row labels already under ``root/submissions``."""
    names, labels = set(), set()
    for y in sorted((Path(root) / "submissions").glob("*/submission.yaml")):
        names.add(y.parent.name)
        try:
            data = yaml.safe_load(y.read_text()) or {}
        except yaml.YAMLError:
            continue  # the leaderboard reports it; its directory name is taken all the same
        if isinstance(data, dict):
            labels.add(str(data.get("entry") or data.get("name") or y.parent.name))
    names |= {p.name for p in (Path(root) / "submissions").glob("*") if p.is_dir()}
    return names, labels


def command_overrides(run: Path) -> list[str] | None:
    """The command-line overrides a finished run recorded in its ``results.json``, or None. Dropped: where it
    ran (``out=``, ``resume=``) and what it did after training (``eval.*``, ``viz.*``) or logged with
    (``train.logger=``): not how it trained, and seeds of one row must record the same training."""
    import json

    try:
        got = json.loads((Path(run) / "results.json").read_text())["meta"]["overrides"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not isinstance(got, list) or not all(isinstance(o, str) for o in got):
        return None
    return [o for o in got if not o.startswith(("out=", "resume=", "eval.", "viz.", "train.logger="))]


def training_overrides(cfg: dict) -> list[str]:
    """The run's ``algo``/``encoder``/``env``/``train`` values that differ from the defaults of its
    algo and encoder, as ``key=value`` overrides (the submission records how it was trained)."""
    from omegaconf import OmegaConf

    from crowdbench.compose import compose

    base = OmegaConf.to_container(compose([f"algo={cfg['algo']['name']}", f"encoder={cfg['encoder']['name']}"]))
    out = [f"algo={cfg['algo']['name']}", f"encoder={cfg['encoder']['name']}"]
    # a wall-time cap or a saved buffer is how a run was kept, not what it learned, except algo=value's
    # max_minutes: the length of its deep V-learning phase (experiment=value_crowdnav)
    skip = {("train", "max_minutes"), ("train", "budget_warm_start"), ("train", "save_buffer"), ("algo", "save_buffer")}
    if cfg["algo"]["name"] != "value":
        skip.add(("algo", "max_minutes"))
    for group in ("algo", "encoder", "env", "train"):
        for key, value in cfg[group].items():
            if base[group].get(key) != value and (group, key) not in skip:
                out.append(f"{group}.{key}={value}")
    return [*out, f"seed={cfg['seed']}"]


def submit_run(run: Path, name: str | None, entry: str | None, authors: list[str], link: str | None,
               notes: str | None, root: Path, overrides: list[str] | None) -> Path:
    """One run -> ``root/submissions/<name>``; name, row label and experiment default to the run's
    ``submission.*`` config; ``overrides``: the command-line overrides of a sweep's run (else derived)."""
    from crowdbench.outputs import OutputError, claim_dir

    try:  # a run still training (it holds the lock) is refused, as `eval` and `run` refuse it
        with claim_dir(Path(run), "run"):
            return _submit_claimed(run, name, entry, authors, link, notes, root, overrides)
    except OutputError as e:
        raise UsageError(f"submit: {e}") from None


def _submit_claimed(run: Path, name, entry, authors, link, notes, root, overrides) -> Path:
    from crowdbench.algos.checkpoint import CheckpointError, load_checkpoint
    from crowdbench.leaderboard import SubmissionError, make_submission

    try:
        cfg = load_checkpoint(run / "checkpoint.pt")["config"]
        meta = cfg.get("submission") or {}
        name, entry = name or meta.get("name"), entry or meta.get("entry")
        if not name or not entry:
            missing = "--name" if not name else "--entry"
            raise UsageError(f"submit: {run} has no submission.{missing[2:]} in its config (train it with "
                             f"method=... or an experiment), pass {missing}")
        if overrides is None and meta.get("experiment"):  # trained with an experiment: its own command line
            overrides = command_overrides(run)
        overrides = list(overrides) if overrides is not None else training_overrides(cfg)
        if not any(o.startswith("seed=") for o in overrides):
            overrides.append(f"seed={cfg['seed']}")
        notes = notes or f"crowdbench run {' '.join(overrides)}"
        return make_submission(run, name, entry, authors, overrides, link, notes, root,
                               experiment=meta.get("experiment"))
    except (CheckpointError, SubmissionError, KeyError) as e:
        raise UsageError(f"submit: {e}") from None
