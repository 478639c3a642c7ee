"""Submissions: the ``submission.yaml`` schema, its validation, reading and writing a submission.

Field reference: docs/submitting.md section 2. Every rejection is a :class:`SubmissionError`,
one line naming the file and the field.
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import yaml

from crowdbench import policies
from crowdbench.leaderboard.tracks import TRACK_ORDER, trained_track

PACKAGE_DIR = Path(__file__).resolve().parents[1]
REPO_DIR = PACKAGE_DIR.parent
DEFAULT_ROOT = Path("leaderboard")  # of the current directory; --root DIR chooses another
KINDS = ("baseline", "learned", "oracle")
BASELINE_POLICIES = policies.BASELINES
ALGOS = ("td3", "ddpg", "sac")
MAX_LEN = 200  # characters of a one-line string field
MAX_LEN_FIELD = {"notes": 2000}


class SubmissionError(Exception):
    """A rejected submission: ``path: field 'x': problem`` on one line."""

    def __init__(self, path: Path | str, fld: str | None, message: str):
        self.path, self.field, self.message = str(path), fld, " ".join(str(message).split())
        where = f"field '{fld}': " if fld else ""
        super().__init__(f"{self.path}: {where}{self.message}")

    def __reduce__(self):  # the custom __init__ needs its three parts to survive pickling (worker processes)
        return SubmissionError, (self.path, self.field, self.message)


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


# field -> (types, required for kinds, description)
SCHEMA: dict[str, tuple[tuple, tuple, str]] = {
    "name": ((str,), KINDS, "the submission's name, equal to its directory name"),
    "kind": ((str,), KINDS, "baseline | learned | oracle"),
    "entry": ((str,), (), "row label; seeds of one method share it (default: name)"),
    "policy": ((str,), ("baseline",), "baseline policy: " + " | ".join(BASELINE_POLICIES)),
    "encoder": ((str,), ("learned",), "registered encoder name (crowdbench.models.ENCODERS)"),
    "encoder_import": ((str,), (), "module:Class of an external encoder, registered under `encoder`"),
    "encoder_entry_points": ((str,), (), "entry-point group to load the encoder from, e.g. crowdbench.encoders"),
    "algo": ((str,), ("learned",), "td3 | ddpg | sac"),
    "experiment": ((str,), (), "the Hydra experiment config the run was trained with, e.g. leaderboard"),
    "track": ((str,), (), "the track the entry was trained on (default v1): " + " | ".join(TRACK_ORDER)),
    "overrides": ((dict, list), (), "baseline/oracle parameters {key: value}; learned: the training overrides"),
    "authors": ((list, str), KINDS, "list of authors"),
    "link": ((str,), (), "paper or code URL"),
    "seed": ((int,), (), "training seed (learned) or policy seed"),
    "privileged": ((bool,), ("oracle",), "true for the oracle (knows the humans' future), false otherwise"),
    "checkpoint": ((str,), (), "checkpoint file name inside the submission directory (default checkpoint.pt)"),
    "notes": ((str,), (), "free text"),
}
LEARNED_ONLY = ("encoder", "encoder_import", "encoder_entry_points", "algo", "checkpoint", "experiment", "track")


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
        limit = MAX_LEN_FIELD.get(key, MAX_LEN)
        if isinstance(v, str) and not 0 < len(v) <= limit:
            raise SubmissionError(path, key, f"must be a non-empty string of at most {limit} characters, "
                                             f"got {len(v)}")
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
    if kind == "learned" and data.get("track", "v1") not in TRACK_ORDER:
        raise SubmissionError(path, "track", f"{data['track']!r} is not a track; valid: {', '.join(TRACK_ORDER)}")
    if kind == "learned" and data["algo"] not in ALGOS:
        raise SubmissionError(path, "algo", f"{data['algo']!r} is not one of {', '.join(ALGOS)}")
    if kind != "learned":
        for key in LEARNED_ONLY:
            if key in data:
                raise SubmissionError(path, key, f"only learned submissions take {key!r}")
    if kind != "learned" and isinstance(data.get("overrides"), list):
        raise SubmissionError(path, "overrides", "baseline/oracle overrides must be a mapping {parameter: value}")
    over = data.get("overrides")
    if kind == "learned" and isinstance(over, list) and not all(isinstance(o, str) for o in over):
        raise SubmissionError(path, "overrides", "a list of key=value strings (the training overrides)")
    return data


def baseline_args(data: dict, cfg: dict | None = None) -> tuple[str, dict, dict]:
    """``(name, cfg, overrides)`` for ``crowdbench.policies.build`` of a baseline / oracle submission:
    ``cfg`` (a track's composed config; default: the default config: env dynamics, ``orca.*`` /
    ``oracle.*``) with the submission's seed."""
    name = "oracle" if data["kind"] == "oracle" else data["policy"]
    return name, {**(cfg or policies.default_config()), "seed": data.get("seed", 0)}, data.get("overrides") or {}


def policy_error(path: Path, e: policies.PolicyError) -> SubmissionError:
    return SubmissionError(path, f"overrides.{e.key}" if e.key else "overrides", str(e))


def policy_params(path: Path, data: dict, cfg: dict | None = None) -> dict:
    """Constructor arguments of a baseline / oracle submission; an unknown override names its key."""
    try:
        return policies.params(*baseline_args(data, cfg))
    except policies.PolicyError as e:
        raise policy_error(path, e) from None


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
                    link: str | None = None, notes: str | None = None, root: Path = DEFAULT_ROOT,
                    experiment: str | None = None) -> Path:
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
    track = trained_track(cfg)
    for key, value in (("experiment", experiment), ("track", None if track == "v1" else track), ("link", link),
                       ("notes", notes)):
        if value:
            data[key] = value
    (sub_dir / "submission.yaml").write_text(yaml.safe_dump(data, sort_keys=False, width=120))
    read_submission(sub_dir)
    return sub_dir


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
        if getattr(module, "__file__", None) and Path(module.__file__) not in sub.extra_files:
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
