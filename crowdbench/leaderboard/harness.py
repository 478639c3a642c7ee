"""The leaderboard harness: validate submissions, evaluate them on protocol v1, generate the table.

Layout (``--root``, default ``leaderboard/`` next to ``crowdbench/``)::

    leaderboard/submissions/<name>/submission.yaml   (+ checkpoint.pt for learned entries)
    leaderboard/results/<name>/results.json           written by the harness, never by hand
    leaderboard/results/oracle/unavoidable.json       episodes the privileged oracle fails
    leaderboard/README.md, leaderboard/leaderboard.png generated

The harness computes every number itself (``crowdbench.eval.evaluate``, the same code as
``crowdbench eval``); submitters only provide a yaml and, for learned entries, a state-dict
checkpoint (``torch.load(..., weights_only=True)``). Field reference: docs/submitting.md.

Cache: ``results.json`` records a fingerprint of everything its numbers depend on (the
submission's files, the encoder module named by ``encoder_import``, the protocol episode
lists, the evaluation options and the source of every crowdbench module an evaluation runs:
``code_files``);
a submission whose fingerprint is unchanged is not re-evaluated unless ``--force``.
``--check`` always re-evaluates everything, writes nothing, and fails if the committed
README differs from the fresh one.
"""

from __future__ import annotations

import argparse
import ast
import functools
import hashlib
import importlib
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import torch
import yaml

from crowdbench.envs.protocol import EVAL_SCENES, PAPER_SCENES, PROTOCOL_DIR, PROTOCOL_VERSION
from crowdbench.eval import evaluate, rate_ci

PACKAGE_DIR = Path(__file__).resolve().parent
REPO_DIR = PACKAGE_DIR.parent
DEFAULT_ROOT = Path("leaderboard")  # of the current directory; --root DIR chooses another
CONFIG_FILE = PACKAGE_DIR / "conf" / "config.yaml"
HARNESS_VERSION = 1
KINDS = ("baseline", "learned", "oracle")
BASELINE_POLICIES = ("orca", "straight")
ALGOS = ("td3", "ddpg", "sac")
# what evaluating a submission runs: the policy builders and the evaluation loop; every crowdbench
# module these import (at any depth) is hashed into the cache fingerprint (code_files)
EVAL_MODULES = ("crowdbench.eval", "crowdbench.algos.checkpoint", "crowdbench.models", "crowdbench.baselines.oracle",
                "crowdbench.baselines.orca", "crowdbench.baselines.straight")
OUTCOME_CHAR = {"success": "S", "collision": "C", "timeout": "T"}
EXTRA_SCENES = tuple(s for s in EVAL_SCENES if s not in PAPER_SCENES)


class SubmissionError(Exception):
    """A rejected submission: ``path: field 'x': problem`` on one line."""

    def __init__(self, path: Path | str, fld: str | None, message: str):
        self.path, self.field, self.message = str(path), fld, " ".join(str(message).split())
        where = f"field '{fld}': " if fld else ""
        super().__init__(f"{self.path}: {where}{self.message}")


@dataclass
class Submission:
    name: str
    dir: Path
    yaml_path: Path
    data: dict
    kind: str
    entry: str
    checkpoint: Path | None = None
    extra_files: list[Path] = field(default_factory=list)  # hashed into the fingerprint


# ---------------------------------------------------------------------------------- schema
# field -> (types, required for kinds, description)
SCHEMA: dict[str, tuple[tuple, tuple, str]] = {
    "name": ((str,), KINDS, "the submission's name, equal to its directory name"),
    "kind": ((str,), KINDS, "baseline | learned | oracle"),
    "entry": ((str,), (), "row label; seeds of one method share it (default: name)"),
    "policy": ((str,), ("baseline",), "baseline policy: orca | straight"),
    "encoder": ((str,), ("learned",), "registered encoder name (crowdbench.models.ENCODERS)"),
    "encoder_import": ((str,), (), "module:Class of an external encoder, registered under `encoder`"),
    "encoder_entry_points": ((str,), (), "entry-point group to load the encoder from, e.g. crowdbench.encoders"),
    "algo": ((str,), ("learned",), "td3 | ddpg | sac"),
    "overrides": ((dict, list), (), "baseline/oracle parameters {key: value}; learned: the training overrides"),
    "authors": ((list, str), KINDS, "list of authors"),
    "link": ((str,), (), "paper or code URL"),
    "seed": ((int,), (), "training seed (learned) or policy seed"),
    "privileged": ((bool,), ("oracle",), "true for the oracle (knows the humans' future), false otherwise"),
    "checkpoint": ((str,), (), "checkpoint file name inside the submission directory (default checkpoint.pt)"),
    "notes": ((str,), (), "free text"),
}


def _config_defaults() -> dict:
    return yaml.safe_load(CONFIG_FILE.read_text()) if CONFIG_FILE.is_file() else {}


def _type_name(types: tuple) -> str:
    return " or ".join({str: "a string", int: "an integer", bool: "true/false", list: "a list",
                        dict: "a mapping"}[t] for t in types)


def validate_schema(path: Path, data) -> dict:
    """Field-level checks of a parsed submission.yaml; returns the data or raises SubmissionError."""
    if not isinstance(data, dict):
        raise SubmissionError(path, None, f"expected a mapping of fields, got {type(data).__name__}")
    for key in data:
        if key not in SCHEMA:
            raise SubmissionError(path, str(key), f"unknown field; valid fields: {', '.join(SCHEMA)}")
    kind = data.get("kind")
    if kind is None:
        raise SubmissionError(path, "kind", "missing (baseline | learned | oracle)")
    if kind not in KINDS:
        raise SubmissionError(path, "kind", f"{kind!r} is not one of {', '.join(KINDS)}")
    for key, (types, required, desc) in SCHEMA.items():
        if key not in data or data[key] is None:
            if kind in required:
                raise SubmissionError(path, key, f"missing ({desc})")
            continue
        v = data[key]
        if not isinstance(v, types) or (int in types and isinstance(v, bool) and bool not in types):
            raise SubmissionError(path, key, f"must be {_type_name(types)}, got {v!r}")
    if data["name"] != path.parent.name:
        raise SubmissionError(path, "name", f"{data['name']!r} differs from the directory name {path.parent.name!r}")
    authors = data["authors"]
    if isinstance(authors, list) and (not authors or not all(isinstance(a, str) and a for a in authors)):
        raise SubmissionError(path, "authors", "must be a non-empty list of names")
    priv = data.get("privileged", False)
    if kind == "oracle" and priv is not True:
        raise SubmissionError(path, "privileged", "the oracle knows the humans' future: it must say privileged: true")
    if kind != "oracle" and priv:
        raise SubmissionError(path, "privileged", "only the oracle may be privileged")
    if kind == "baseline" and data["policy"] not in BASELINE_POLICIES:
        raise SubmissionError(path, "policy", f"{data['policy']!r} is not a baseline; valid: "
                                              f"{', '.join(BASELINE_POLICIES)}")
    if kind == "learned" and data["algo"] not in ALGOS:
        raise SubmissionError(path, "algo", f"{data['algo']!r} is not one of {', '.join(ALGOS)}")
    if kind != "learned":
        for key in ("encoder", "encoder_import", "encoder_entry_points", "algo", "checkpoint"):
            if key in data:
                raise SubmissionError(path, key, f"only learned submissions take {key!r}")
    if kind != "learned" and isinstance(data.get("overrides"), list):
        raise SubmissionError(path, "overrides", "baseline/oracle overrides must be a mapping {parameter: value}")
    over = data.get("overrides")
    if kind == "learned" and isinstance(over, list) and not all(isinstance(o, str) for o in over):
        raise SubmissionError(path, "overrides", "a list of key=value strings (the training overrides)")
    return data


def policy_params(path: Path, data: dict) -> dict:
    """Baseline / oracle parameters: the config's defaults (``orca.*`` / ``oracle.*``) + the overrides."""
    policy = "oracle" if data["kind"] == "oracle" else data["policy"]
    defaults = dict(_config_defaults().get(policy) or {})
    params = dict(defaults)
    over = data.get("overrides") or {}
    for key, value in over.items():
        k = key.split(".", 1)[1] if key.startswith(f"{policy}.") else key
        if k == "seed" or k in defaults:
            params[k] = value
        else:
            valid = ", ".join(sorted(defaults)) or "none"
            raise SubmissionError(path, f"overrides.{key}", f"unknown {policy} parameter; valid: {valid}")
    return params


def read_submission(sub_dir: Path) -> Submission:
    path = sub_dir / "submission.yaml"
    if not path.is_file():
        raise SubmissionError(path, None, "missing submission.yaml")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e)
        raise SubmissionError(path, None, f"malformed YAML{where}: {problem}") from None
    data = validate_schema(path, data)
    sub = Submission(name=data["name"], dir=sub_dir, yaml_path=path, data=data, kind=data["kind"],
                     entry=data.get("entry") or data["name"])
    if sub.kind == "learned":
        sub.checkpoint = sub_dir / data.get("checkpoint", "checkpoint.pt")
        if not sub.checkpoint.is_file():
            raise SubmissionError(path, "checkpoint", f"checkpoint file not found: {sub.checkpoint}")
    else:
        policy_params(path, data)
    return sub


def make_submission(run_dir: Path, name: str, entry: str, authors: list[str], overrides: list[str],
                    link: str | None = None, notes: str | None = None, root: Path = DEFAULT_ROOT) -> Path:
    """``leaderboard/submissions/<name>/`` from a training run: a slim checkpoint + submission.yaml.

    The checkpoint keeps what evaluation needs (config, actor weights, frames, updates, wall
    time) and drops the critics and optimiser states (~7x smaller). The yaml is then read back
    through :func:`read_submission`, so a submission this writes is one the harness accepts."""
    from crowdbench.algos.checkpoint import load_checkpoint, save_checkpoint

    state = load_checkpoint(Path(run_dir) / "checkpoint.pt")
    cfg = state["config"]
    sub_dir = Path(root) / "submissions" / name
    if sub_dir.exists():
        raise SubmissionError(sub_dir, None, "already exists; remove it first to replace the submission")
    sub_dir.mkdir(parents=True)
    keep = ("config", "actor", "frames", "updates", "wall_time_s")
    save_checkpoint(sub_dir / "checkpoint.pt", {k: state[k] for k in keep if k in state})
    data = {"name": name, "kind": "learned", "entry": entry, "encoder": cfg["encoder"]["name"],
            "algo": cfg["algo"]["name"], "seed": int(cfg["seed"]), "overrides": overrides, "authors": authors}
    if link:
        data["link"] = link
    if notes:
        data["notes"] = notes
    (sub_dir / "submission.yaml").write_text(yaml.safe_dump(data, sort_keys=False, width=120))
    read_submission(sub_dir)
    return sub_dir


# ---------------------------------------------------------------------------------- encoders
def register_encoder(sub: Submission) -> None:
    """Make ``sub``'s encoder known: an import path or an entry point registers it into ENCODERS."""
    from torch import nn

    from crowdbench.models import ENCODERS

    data, path, name = sub.data, sub.yaml_path, sub.data["encoder"]
    cls = None
    if "encoder_import" in data:
        spec = data["encoder_import"]
        mod_name, _, attr = spec.partition(":")
        if not mod_name or not attr:
            raise SubmissionError(path, "encoder_import", f"{spec!r} is not of the form module:Class")
        added = [p for p in (str(sub.dir), str(REPO_DIR), str(Path.cwd())) if p not in sys.path]
        sys.path[:0] = added
        try:
            module = importlib.import_module(mod_name)
        except Exception as e:  # noqa: BLE001 - any import failure is the submission's error
            raise SubmissionError(path, "encoder_import", f"cannot import {mod_name!r}: {type(e).__name__}: {e}") \
                from None
        finally:
            for p in added:
                sys.path.remove(p)
        cls = getattr(module, attr, None)
        if cls is None:
            raise SubmissionError(path, "encoder_import", f"module {mod_name!r} has no attribute {attr!r}")
        if getattr(module, "__file__", None):
            sub.extra_files.append(Path(module.__file__))
    elif "encoder_entry_points" in data:
        group = data["encoder_entry_points"]
        found = [ep for ep in metadata.entry_points(group=group) if ep.name == name]
        if not found:
            raise SubmissionError(path, "encoder_entry_points",
                                  f"no entry point {name!r} in group {group!r} (is the package installed?)")
        try:
            cls = found[0].load()
        except Exception as e:  # noqa: BLE001
            raise SubmissionError(path, "encoder_entry_points", f"cannot load {found[0].value!r}: {e}") from None
    if cls is not None:
        if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
            raise SubmissionError(path, "encoder_import" if "encoder_import" in data else "encoder_entry_points",
                                  f"{cls!r} is not a torch.nn.Module subclass")
        if ENCODERS.get(name, cls) is not cls:
            raise SubmissionError(path, "encoder", f"{name!r} is already registered to another class "
                                                   f"({ENCODERS[name].__module__}.{ENCODERS[name].__name__})")
        ENCODERS[name] = cls
    if name not in ENCODERS:
        raise SubmissionError(path, "encoder", f"unknown encoder {name!r}; registered: {', '.join(sorted(ENCODERS))} "
                                               "(an external encoder needs encoder_import or encoder_entry_points)")


# ---------------------------------------------------------------------------------- policies
def dummy_obs(batch: int = 2, humans: int = 3):
    from crowdbench.envs.policy import obs_tensordict

    g = torch.Generator().manual_seed(0)
    robot = torch.zeros(batch, 1, 6)
    robot[..., 4] = 4.0
    h = torch.randn(batch, 1, humans, 4, generator=g)
    mask = torch.ones(batch, 1, humans, dtype=torch.bool)
    return obs_tensordict({"robot": robot, "humans": h, "humans_mask": mask}, batch)


def build_policy(sub: Submission):
    """The :class:`~crowdbench.envs.policy.Policy` of a validated submission (learned: loaded safely)."""
    d, path = sub.data, sub.yaml_path
    if sub.kind == "learned":
        from crowdbench.algos.checkpoint import CheckpointError, load_checkpoint, policy_from_checkpoint

        register_encoder(sub)
        try:
            state = load_checkpoint(sub.checkpoint)  # weights_only=True: never runs pickled code
        except CheckpointError as e:
            raise SubmissionError(path, "checkpoint", str(e)) from None
        cfg = state["config"]
        try:
            c_enc, c_algo = cfg["encoder"]["name"], cfg["algo"]["name"]
            _ = cfg["env"]["v_max"], cfg["env"]["frame"]
        except (KeyError, TypeError) as e:
            raise SubmissionError(path, "checkpoint", f"{sub.checkpoint}: config lacks {e}") from None
        if c_enc != d["encoder"]:
            raise SubmissionError(path, "encoder", f"{d['encoder']!r} but the checkpoint was trained with {c_enc!r}")
        if c_algo != d["algo"]:
            raise SubmissionError(path, "algo", f"{d['algo']!r} but the checkpoint was trained with {c_algo!r}")
        try:
            policy = policy_from_checkpoint(sub.checkpoint)
        except CheckpointError as e:
            raise SubmissionError(path, "checkpoint", str(e)) from None
        try:
            out = policy.act(dummy_obs())
        except Exception as e:  # noqa: BLE001 - a model that cannot act on an observation is rejected
            raise SubmissionError(path, "checkpoint", f"the model fails on an observation: {type(e).__name__}: {e}") \
                from None
        if tuple(out.shape) != (2, 1, 2) or not torch.isfinite(out).all():
            raise SubmissionError(path, "checkpoint", f"the model returns actions of shape {tuple(out.shape)} "
                                                      "(expected [B, 1, 2], finite)")
    else:
        params = policy_params(path, d)
        try:
            if sub.kind == "oracle":
                from crowdbench.baselines.oracle import Oracle

                policy = Oracle(**params)
            elif d["policy"] == "orca":
                from crowdbench.baselines.orca import ORCA

                policy = ORCA(**{"seed": d.get("seed", 0), **params})
            else:
                from crowdbench.baselines.straight import StraightToGoal

                policy = StraightToGoal(**params)
        except (TypeError, ValueError) as e:
            raise SubmissionError(path, "overrides", str(e)) from None
    policy.name = sub.name
    return policy


# ---------------------------------------------------------------------------------- fingerprint
def _sha(h, path: Path) -> None:
    h.update(str(path.name).encode())
    h.update(path.read_bytes())


def _module_file(name: str) -> Path | None:
    """``crowdbench.a.b`` -> its source file; None for a name that is not a module (an imported attribute)."""
    base = REPO_DIR.joinpath(*name.split("."))
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    return base.with_suffix(".py") if base.with_suffix(".py").is_file() else None


@functools.cache  # one walk per process, not one per submission (~50 ms each)
def code_files(roots=EVAL_MODULES) -> tuple[Path, ...]:
    """Source files of ``roots`` and of every crowdbench module they import, directly or not, with
    the packages' ``__init__.py`` (read statically with ``ast``, including imports inside functions).

    Why not all of ``crowdbench/``: training code (algos/train.py, learner.py) never runs in an
    evaluation, and hashing it made every training change mark all cached results stale.
    tests/test_leaderboard.py checks that every module an evaluation loads is in this list."""
    seen: set[Path] = set()
    todo = list(roots)
    while todo:
        parts = todo.pop().split(".")
        for i in range(1, len(parts) + 1):  # importing a.b.c runs a and a.b first
            path = _module_file(".".join(parts[:i]))
            if path is None or path in seen:
                continue
            seen.add(path)
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("crowdbench"):
                    todo += [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
                elif isinstance(node, ast.Import):
                    todo += [a.name for a in node.names if a.name.startswith("crowdbench")]
    return tuple(sorted(seen))


def fingerprint(sub: Submission, scenes: list[str], episodes: int | None) -> str:
    h = hashlib.sha256()
    h.update(json.dumps({"harness": HARNESS_VERSION, "protocol": PROTOCOL_VERSION, "scenes": scenes,
                         "episodes": episodes, "defaults": _config_defaults().get(
                             "oracle" if sub.kind == "oracle" else sub.data.get("policy", ""))},
                        sort_keys=True).encode())
    for p in [sub.yaml_path, *([sub.checkpoint] if sub.checkpoint else []), *sub.extra_files]:
        _sha(h, p)
    for s in scenes:
        _sha(h, PROTOCOL_DIR / f"{s}.json")
    for f in code_files():
        _sha(h, f)
    return h.hexdigest()


# ---------------------------------------------------------------------------------- evaluation
def evaluate_submission(sub: Submission, policy, scenes: list[str], episodes: int | None, fp: str) -> dict:
    """Run the protocol with ``crowdbench.eval.evaluate``; add per-episode outcome strings."""
    with tempfile.TemporaryDirectory() as tmp:
        res = evaluate(policy, scenes, episodes, out_dir=Path(tmp), save_episodes=True,
                       sim_overrides={"frame": policy.frame},
                       meta={"submission": sub.name, "kind": sub.kind, "entry": sub.entry})
        rows = [json.loads(line) for line in (Path(tmp) / "episodes.jsonl").read_text().splitlines()]
    outcomes: dict[str, list] = {s: [] for s in scenes}
    for r in rows:
        outcomes[r["scene"]].append((r["episode"], OUTCOME_CHAR[r["outcome"]]))
    res["episode_ids"] = {s: [e for e, _ in v] for s, v in outcomes.items()}
    res["episode_outcomes"] = {s: "".join(c for _, c in v) for s, v in outcomes.items()}
    res["submission"] = sub.data
    res["harness"] = {"version": HARNESS_VERSION, "scenes": scenes, "episodes": episodes,
                      "official": episodes is None and set(scenes) == set(EVAL_SCENES), "fingerprint": fp}
    if sub.kind == "oracle":
        res["privileged"] = True
        res["unavoidable"] = unavoidable(res)
    return res


def unavoidable(res: dict) -> dict:
    """Episodes the oracle fails: candidate unavoidable collisions (and timeouts), per scene."""
    out = {}
    for s, chars in res["episode_outcomes"].items():
        ids = res["episode_ids"][s]
        out[s] = {"collision": [ids[i] for i, c in enumerate(chars) if c == "C"],
                  "timeout": [ids[i] for i, c in enumerate(chars) if c == "T"], "episodes": len(chars)}
    return out


# ---------------------------------------------------------------------------------- tables
def _fmt(v, digits: int) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def scene_cell(r: dict, scene: str, metric: str, digits: int) -> tuple[float | None, str]:
    v = r["scenes"].get(scene, {}).get(metric)
    if not v or v["mean"] is None:
        return None, "—"
    return v["mean"], f"{v['mean']:.{digits}f} [{v['ci95'][0]:.{digits}f}, {v['ci95'][1]:.{digits}f}]"


def average_cell(r: dict, metric: str, digits: int) -> tuple[float | None, str]:
    """Paper-scene average: pooled Wilson interval for rates, combined normal interval for means."""
    vals = [r["scenes"].get(s, {}).get(metric) for s in PAPER_SCENES]
    if any(v is None or v["mean"] is None for v in vals):
        return None, "—"
    mean = sum(v["mean"] for v in vals) / len(vals)
    if metric.endswith("_rate"):
        n = sum(v["n"] for v in vals)
        k = round(sum(v["mean"] * v["n"] for v in vals))
        ci = rate_ci(k, n)["ci95"] if len({v["n"] for v in vals}) == 1 else [None, None]
    else:
        half = math.sqrt(sum(((v["ci95"][1] - v["ci95"][0]) / 2) ** 2 for v in vals)) / len(vals)
        ci = [mean - half, mean + half]
    if ci[0] is None:
        return mean, _fmt(mean, digits)
    return mean, f"{mean:.{digits}f} [{ci[0]:.{digits}f}, {ci[1]:.{digits}f}]"


def seed_cell(values: list[float | None], digits: int) -> tuple[float | None, str]:
    """Mean ± standard deviation over seeds (and the number of seeds)."""
    if not values or any(v is None for v in values):
        return None, "—"
    m = sum(values) / len(values)
    sd = math.sqrt(sum((v - m) ** 2 for v in values) / (len(values) - 1)) if len(values) > 1 else 0.0
    return m, f"{m:.{digits}f} ± {sd:.{digits}f}"


def label(group: list[dict]) -> str:
    r = group[0]
    name = r["meta"]["entry"]
    if r.get("privileged") and "privileged" not in name.lower():
        name += " (PRIVILEGED)"
    return name


def group_results(results: list[dict]) -> list[list[dict]]:
    """Results grouped by entry (seeds together), ordered baseline < learned < oracle, then by name."""
    groups: dict[str, list[dict]] = {}
    for r in sorted(results, key=lambda r: r["meta"]["submission"]):
        groups.setdefault(r["meta"]["entry"], []).append(r)
    order = {k: i for i, k in enumerate(KINDS)}
    return sorted(groups.values(), key=lambda g: (order[g[0]["meta"]["kind"]], g[0]["meta"]["entry"].lower()))


METRICS = [
    ("success_rate", "Success rate (Tables III / IV)", 3),
    ("nav_time_s", "Navigation time, s, successful episodes (Tables III / IV)", 2),
    ("dangers_per_episode", "Dangers per episode, steps with 0 <= d < 0.2 m (Table V)", 3),
    ("collision_rate", "Collision rate", 3),
    ("timeout_rate", "Timeout rate", 3),
]


def metric_table(groups: list[list[dict]], scenes: list[str], metric: str, digits: int) -> list[str]:
    paper = [s for s in PAPER_SCENES if s in scenes]
    extra = [s for s in scenes if s not in PAPER_SCENES]
    with_avg = len(paper) == len(PAPER_SCENES)
    head = ["method", "seeds", *paper, *(["AVG (paper scenes)"] if with_avg else []), *extra]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g in groups:
        cells = [label(g), str(len(g))]
        for col in head[2:]:
            if len(g) == 1:
                _, c = average_cell(g[0], metric, digits) if col.startswith("AVG") else \
                    scene_cell(g[0], col, metric, digits)
            else:
                vals = [(average_cell(r, metric, digits) if col.startswith("AVG") else
                         scene_cell(r, col, metric, digits))[0] for r in g]
                _, c = seed_cell(vals, digits)
            cells.append(c)
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def render_readme(results: list[dict], rejected: list[str], scenes: list[str], episodes: int | None,
                  missing: list[str]) -> str:
    groups = group_results(results)
    official = episodes is None and set(scenes) == set(EVAL_SCENES)
    L = [("<!-- GENERATED by `crowdbench leaderboard` from leaderboard/results/*/results.json: DO NOT EDIT BY HAND."
         " `crowdbench leaderboard --check` fails if this file differs from a fresh evaluation. -->"), "",
         "# crowdbench leaderboard (protocol " + PROTOCOL_VERSION + ")", ""]
    if official:
        L.append("Every number is computed by the harness (`crowdbench leaderboard`) on the fixed protocol: 250 episodes "
                 "per scene, 4 paper scenes (students003, zara2, hotel, eth) and 3 extra scenes (zara1, zara3, "
                 "uni_examples). Single runs: mean [95% interval] (Wilson for rates, normal approximation for means; "
                 "the paper-scene average pools the four scenes). Entries with several training seeds: mean ± "
                 "standard deviation across seeds (per-seed rows below).")
    else:
        L.append(f"**UNOFFICIAL subset**: {episodes or 250} episodes per scene, scenes {', '.join(scenes)}. "
                 "Not comparable with the official table.")
    L += ["", ("The **oracle** is PRIVILEGED: it knows every replayed human's future and plans with the simulator's "
          "own collision test. It is an upper bound on what is achievable, not a navigation policy. "
          "How to submit: [docs/submitting.md](../docs/submitting.md)."), "", "![leaderboard](leaderboard.png)", ""]
    for metric, title, digits in METRICS:
        L += [f"## {title}", "", *metric_table(groups, scenes, metric, digits), ""]
    oracle = [r for g in groups for r in g if r["meta"]["kind"] == "oracle"]
    if oracle:
        u = oracle[0]["unavoidable"]
        L += ["## Unavoidable episodes (oracle failures)", "",
              ("Episodes in which the privileged oracle fails are candidate unavoidable collisions (its search is "
              "not exhaustive, so each is a candidate, not a proof); the list is in "
              f"`results/{oracle[0]['meta']['submission']}/unavoidable.json`."), "",
              "| scene | episodes | oracle collisions | oracle timeouts |", "|---|---|---|---|"]
        for s in scenes:
            if s in u:
                L.append(f"| {s} | {u[s]['episodes']} | {len(u[s]['collision'])} | {len(u[s]['timeout'])} |")
        L.append("")
    multi = [g for g in groups if len(g) > 1]
    if multi:
        L += ["## Per-seed results (success rate)", "", "| entry | submission | seed | " + " | ".join(scenes) + " |",
              "|" + "---|" * (3 + len(scenes))]
        for g in multi:
            for r in g:
                cells = [scene_cell(r, s, "success_rate", 3)[1] for s in scenes]
                L.append(f"| {label(g)} | {r['meta']['submission']} | {r['submission'].get('seed', '—')} | "
                         + " | ".join(cells) + " |")
        L.append("")
    L += ["## Submissions", "", "| submission | entry | kind | encoder | algo | seed | authors | link |",
          "|---|---|---|---|---|---|---|---|"]
    for g in groups:
        for r in g:
            d = r["submission"]
            authors = d["authors"] if isinstance(d["authors"], str) else ", ".join(d["authors"])
            kind = d["kind"] + (" (privileged)" if d.get("privileged") else "")
            L.append(f"| {d['name']} | {label(g)} | {kind} | {d.get('encoder', d.get('policy', '—'))} | "
                     f"{d.get('algo', '—')} | {d.get('seed', '—')} | {authors} | {d.get('link', '—')} |")
    L.append("")
    if missing:
        L += ["## Not evaluated", "", *[f"- {m}" for m in missing], ""]
    if rejected:
        L += ["## Rejected submissions", "", *[f"- {e}" for e in rejected], ""]
    return "\n".join(L)


def plot(results: list[dict], scenes: list[str], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = group_results(results)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2))
    width = 0.8 / max(len(groups), 1)
    xs = range(len(scenes))
    for i, g in enumerate(groups):
        for ax, metric in zip(axes, ("success_rate", "dangers_per_episode"), strict=True):
            means, lo, hi = [], [], []
            for s in scenes:
                vals = [r["scenes"][s][metric] for r in g if s in r["scenes"]]
                m = sum(v["mean"] for v in vals) / len(vals) if vals else float("nan")
                if len(g) == 1 and vals:
                    a, b = vals[0]["ci95"]
                else:
                    sd = torch.tensor([v["mean"] for v in vals], dtype=torch.float64).std().item() if vals else 0
                    a, b = m - sd, m + sd
                means.append(m)
                lo.append(max(m - a, 0))
                hi.append(max(b - m, 0))
            ax.bar([x + (i - (len(groups) - 1) / 2) * width for x in xs], means, width, yerr=[lo, hi], capsize=2,
                   label=label(g), color=plt.get_cmap("tab20")(i % 20))
    for ax, title in zip(axes, ("success rate (95% CI; seeds: ± sd)", "dangers per episode"), strict=True):
        ax.set_xticks(list(xs), scenes, rotation=30, ha="right")
        ax.set_title(title)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylim(0, 1.05)
    handles, labels = axes[0].get_legend_handles_labels()
    ncol = min(len(groups), 4)
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=8, frameon=False)
    fig.suptitle(f"crowdbench leaderboard, protocol {PROTOCOL_VERSION} (oracle = privileged upper bound)")
    fig.tight_layout(rect=(0, 0.04 + 0.035 * math.ceil(len(groups) / ncol), 1, 1))
    fig.savefig(out, dpi=110, metadata={"Software": None})
    plt.close(fig)


def diff_rows(old: str, new: str) -> list[str]:
    """Rows that differ between two generated READMEs, named by section and first cell."""
    def rows(text):
        out, section = {}, ""
        for line in text.splitlines():
            if line.startswith("#"):
                section = line.lstrip("# ").strip()
            elif line.startswith("| ") and not line.startswith("|---"):
                key = (section, line.split("|")[1].strip())
                while key in out:
                    key = (key[0], key[1] + "'")
                out[key] = line
            elif line.strip():
                out[(section, line.strip()[:60])] = line
        return out

    a, b = rows(old), rows(new)
    msgs = []
    for key in list(dict.fromkeys([*a, *b])):
        if a.get(key) != b.get(key):
            state = "missing in committed" if key not in a else "missing in fresh" if key not in b else "differs"
            msgs.append(f"[{key[0]}] row '{key[1]}': {state}" +
                        (f"\n    committed: {a[key]}\n    fresh:     {b[key]}" if state == "differs" else ""))
    return msgs


# ---------------------------------------------------------------------------------- main
def _job(sub: Submission, scenes: list[str], episodes: int | None, fp: str):
    """Evaluate one validated submission: ``(results, seconds)`` or the :class:`SubmissionError`.

    Single-threaded (``torch.set_num_threads(1)``) whatever the caller's setting, so the
    floating-point reductions, and hence the numbers, do not depend on the machine or ``--jobs``.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        t = time.time()
        res = evaluate_submission(sub, build_policy(sub), scenes, episodes, fp)
        return res, time.time() - t
    except SubmissionError as e:
        return e
    finally:
        torch.set_num_threads(threads)


def _job_in_worker(sub: Submission, scenes, episodes, fp):
    out = _job(sub, scenes, episodes, fp)
    # SubmissionError has a custom __init__ and does not survive pickling: send its parts
    return ("error", out.path, out.field, out.message) if isinstance(out, SubmissionError) else ("ok", out)


def _evaluate_all(todo: list, scenes: list[str], episodes: int | None, jobs: int):
    """Yield ``(dir, submission, results path, (results, seconds) | SubmissionError)`` in ``todo`` order."""
    if jobs <= 1 or len(todo) <= 1:
        for d, sub, fp, res_path in todo:
            yield d, sub, res_path, _job(sub, scenes, episodes, fp)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
        futures = [pool.submit(_job_in_worker, sub, scenes, episodes, fp) for _, sub, fp, _ in todo]
        for (d, sub, _, res_path), fut in zip(todo, futures, strict=True):
            out = fut.result()
            yield d, sub, res_path, SubmissionError(*out[1:]) if out[0] == "error" else out[1]


def run(root: Path = DEFAULT_ROOT, only: list[str] | None = None, check: bool = False, force: bool = False,
        episodes: int | None = None, scenes: list[str] | None = None, log=None, jobs: int = 1) -> int:
    """Validate, evaluate and render; returns the exit code (0 ok, 1 a submission failed or --check differs)."""
    root = Path(root)
    log = log or (lambda msg: print(msg, flush=True))
    scenes = list(scenes or EVAL_SCENES)
    sub_root = root / "submissions"
    dirs = sorted(p for p in sub_root.iterdir() if p.is_dir()) if sub_root.is_dir() else []
    if not dirs:
        log(f"crowdbench leaderboard: error: no submissions under {sub_root}")
        return 1
    names = [d.name for d in dirs]
    unknown = [n for n in (only or []) if n not in names]
    if unknown:
        log(f"crowdbench leaderboard: error: unknown submission(s) {', '.join(unknown)}; known: {', '.join(names)}")
        return 1
    results, rejected, missing, todo = [], [], [], []
    t_all = time.time()

    def reject(e: SubmissionError) -> None:
        log(f"crowdbench leaderboard: error: {e}")
        rejected.append(str(e).replace(str(root.resolve()) + "/", "").replace(str(root) + "/", ""))

    for d in dirs:
        res_path = root / "results" / d.name / "results.json"
        selected = only is None or d.name in only
        try:
            sub = read_submission(d)
            if sub.kind == "learned":
                register_encoder(sub)
            fp = fingerprint(sub, scenes, episodes)
            cached = json.loads(res_path.read_text()) if res_path.is_file() else None
            fresh = cached is not None and cached.get("harness", {}).get("fingerprint") == fp
            if not check and (fresh and not force or not selected):
                if fresh:
                    results.append(cached)
                    if selected:
                        log(f"{d.name}: unchanged, cached results ({res_path.relative_to(root)}); --force re-evaluates")
                else:
                    missing.append(f"{d.name}: results missing or out of date (`crowdbench leaderboard --only {d.name}`)")
                continue
            todo.append((d, sub, fp, res_path))
        except SubmissionError as e:
            reject(e)
    for d, sub, res_path, outcome in _evaluate_all(todo, scenes, episodes, jobs):
        if isinstance(outcome, SubmissionError):
            reject(outcome)
            continue
        res, seconds = outcome
        log(f"{d.name}: evaluated in {seconds:.1f} s; average success (paper scenes) "
            f"{_fmt(res.get('average_paper_scenes', {}).get('success_rate'), 3)}")
        results.append(res)
        if not check:
            res_path.parent.mkdir(parents=True, exist_ok=True)
            res_path.write_text(json.dumps(res, indent=1) + "\n")
            if sub.kind == "oracle":
                (res_path.parent / "unavoidable.json").write_text(json.dumps(
                    {"privileged": True, "note": "episodes the privileged oracle fails: candidate unavoidable",
                     "protocol": PROTOCOL_VERSION, "scenes": res["unavoidable"]}, indent=1) + "\n")
    rejected.sort()
    failed = bool(rejected)
    readme = render_readme(results, rejected, scenes, episodes, missing)
    log(f"leaderboard: {len(results)} evaluated/cached, {len(rejected)} rejected, {time.time() - t_all:.1f} s")
    if check:
        committed = (root / "README.md").read_text() if (root / "README.md").is_file() else ""
        if committed != readme:
            diffs = diff_rows(committed, readme) or ["(whitespace or layout)"]
            log("crowdbench leaderboard --check: FAILED: leaderboard/README.md differs from a fresh evaluation in "
                f"{len(diffs)} row(s):\n  " + "\n  ".join(diffs))
            return 1
        log("crowdbench leaderboard --check: README.md matches a fresh evaluation")
        return 1 if failed else 0
    (root / "README.md").write_text(readme)
    if results:
        plot(results, scenes, root / "leaderboard.png")
    log(f"wrote {root / 'README.md'} and {root / 'leaderboard.png'}")
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    from crowdbench.data.scenes import check_scene

    ap = argparse.ArgumentParser(prog="crowdbench leaderboard",
                                 description="Validate and evaluate leaderboard submissions; regenerate the table.")
    ap.add_argument("--check", action="store_true", help="re-evaluate everything (no cache, nothing written); "
                    "exit 1 if leaderboard/README.md differs from the fresh result")
    ap.add_argument("--force", action="store_true", help="re-evaluate even unchanged submissions")
    ap.add_argument("--only", action="append", metavar="NAME", help="evaluate only this submission (repeatable); "
                    "the others keep their cached results")
    ap.add_argument("--episodes", type=int, default=None, help="N episodes per scene (evenly strided; unofficial)")
    ap.add_argument("--scenes", default=None, help="comma-separated scene subset (unofficial)")
    ap.add_argument("--jobs", type=int, default=1, help="evaluate N submissions in parallel processes "
                    "(each single-threaded; the numbers do not depend on N)")
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT, help=f"leaderboard directory (default {DEFAULT_ROOT})")
    args = ap.parse_args(argv)
    if args.episodes is not None and args.episodes < 1:
        ap.error("--episodes must be >= 1")
    scenes = None
    if args.scenes:
        try:
            scenes = [check_scene(s.strip()) for s in args.scenes.split(",") if s.strip()]
        except ValueError as e:
            ap.error(str(e))
        bad = [s for s in scenes if s not in EVAL_SCENES]
        if bad:
            ap.error(f"not an evaluation scene: {', '.join(bad)}; valid: {', '.join(EVAL_SCENES)}")
    if args.jobs < 1:
        ap.error("--jobs must be >= 1")
    return run(args.root, args.only, args.check, args.force, args.episodes, scenes, jobs=args.jobs)


__all__ = ["SubmissionError", "main", "make_submission", "read_submission", "render_readme", "run"]
