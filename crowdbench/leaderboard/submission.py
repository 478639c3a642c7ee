"""Submissions: the ``submission.yaml`` schema, its validation, reading and writing a submission.

Field reference and rules: docs/submitting.md section 2. Every rejection is a :class:`SubmissionError`,
one line naming the file and the field, of bounded length (values are cut short, :func:`short`).
A submission is confined to its directory: its name, files and encoder module (:func:`inside`).
"""

from __future__ import annotations

import os
import re
import shutil
import unicodedata
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import yaml

from crowdbench import policies
from crowdbench.algos.registry import names as algo_names
from crowdbench.config_fields import SEED_BOUNDS, problem, value_range
from crowdbench.envs.lookahead import MODELS as LOOKAHEAD_MODELS
from crowdbench.envs.lookahead import PRIVILEGED_MODELS
from crowdbench.leaderboard.text import bad_char, one_line, short
from crowdbench.leaderboard.tracks import trained_track
from crowdbench.models.value_nets import NETS as VALUE_NETS
from crowdbench.outputs import pid_dir
from crowdbench.protocols import homes

PACKAGE_DIR = Path(__file__).resolve().parents[1]
REPO_DIR = PACKAGE_DIR.parent
DEFAULT_ROOT = Path("leaderboard")  # of the current directory; --root DIR chooses another
KINDS = ("baseline", "learned", "oracle")
BASELINE_POLICIES = policies.BASELINES
MAX_LEN = 200  # characters of a one-line string field
MAX_LEN_FIELD = {"notes": 2000}
MULTILINE = ("notes",)  # the only string field that may hold newlines (it is never shown in a table)
MAX_BYTES = 64 * 1024  # of submission.yaml
MAX_FILE_BYTES = 256 * 1024 ** 2  # of a checkpoint or an encoder module (the published ones: < 1 MB)
MAX_DEPTH = 8  # nesting of YAML collections
MAX_ITEMS = {"authors": 20, "overrides": 200}
MAX_MESSAGE = 320  # characters of a SubmissionError's problem
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # and no "..": a directory name, never a path
NAME_RULE = "1-64 letters, digits, '_', '.', '-', starting with a letter or digit, no '..'"
WORD_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # encoder names, entry-point groups
IMPORT_RE = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*", re.ASCII)
# http(s), a host, then characters that need no escaping in markdown (no space, quote, <, >, |, [, ], `, *)
LINK_RE = re.compile(r"https?://[A-Za-z0-9\-._~:/?#@!$&+,;=%()]+")
LINK_RULE = "an http:// or https:// URL with a host (no spaces, quotes, <, >, |, [, ], `, *)"


class SubmissionError(Exception):
    """A rejected submission: ``path: field 'x': problem`` on one line of bounded length."""

    def __init__(self, path: Path | str, fld: str | None, message: str, public: str | None = None):
        self.path, self.field, self.message = str(path), fld, one_line(message)
        if len(self.message) > MAX_MESSAGE:
            self.message = self.message[:MAX_MESSAGE] + "..."
        self.where = f"{one_line(self.path)}: " + (f"field '{one_line(fld)[:60]}': " if fld else "")
        self.public_message = None if public is None else one_line(public)[:MAX_MESSAGE]
        super().__init__(f"{self.where}{self.message}")

    @property
    def public(self) -> str:
        """What the README shows: without text a worker wrote (the log has the whole message)."""
        return str(self) if self.public_message is None else f"{self.where}{self.public_message}"

    def __reduce__(self):  # the custom __init__ needs its parts to survive pickling (worker processes)
        return SubmissionError, (self.path, self.field, self.message, self.public_message)


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
    "algo": ((str,), ("learned",), "the training algorithm (crowdbench.algos registry): td3 | ddpg | sac | ppo | value"),
    "experiment": ((str,), (), "the Hydra experiment config the run was trained with, e.g. leaderboard"),
    "track": ((str,), (), "the track the entry was trained on (default v1; selfplay: self-play): " + " | ".join(homes())),
    "overrides": ((dict, list), (), "baseline/oracle parameters {key: value}; learned: the training overrides"),
    "authors": ((list, str), KINDS, "list of authors"),
    "link": ((str,), (), "paper or code URL"),
    "seed": ((int,), (), "training seed (learned) or policy seed"),
    "privileged": ((bool,), ("oracle",), ("true for the oracle (knows the humans' future) and for a value entry "
                                          "with lookahead: query (reads the humans' next states); false otherwise")),
    "lookahead": ((str,), (), ("algo value: the humans' next-state model its candidates are computed with: "
                               + " | ".join(LOOKAHEAD_MODELS) + " (query: privileged)")),
    "net": ((str,), (), ("algo value: its value network: " + " | ".join(VALUE_NETS)
                         + " (encoder: the entry's `encoder` with a value head)")),
    "checkpoint": ((str,), (), "checkpoint file name inside the submission directory (default checkpoint.pt)"),
    "notes": ((str,), (), "free text"),
}
LEARNED_ONLY = ("encoder", "encoder_import", "encoder_entry_points", "algo", "checkpoint", "experiment", "track",
                "lookahead", "net")


def name_problem(name) -> str | None:
    """Why ``name`` is not a valid submission (directory) name, or None."""
    if isinstance(name, str) and NAME_RE.fullmatch(name) and ".." not in name:
        return None
    return f"{short(name)} is not a valid submission name ({NAME_RULE})"


def link_problem(link) -> str | None:
    """Why ``link`` is not an acceptable ``link`` (an http(s) URL with a host), or None."""
    try:
        parts = urlsplit(link) if isinstance(link, str) and LINK_RE.fullmatch(link) else None
        ok = parts is not None and bool(parts.hostname) and (parts.port or 1) > 0
    except ValueError:  # e.g. a port that is not a number
        ok = False
    return None if ok else f"must be {LINK_RULE}, got {short(link)}"


def _text_problem(key: str, v: str) -> str | None:
    limit = MAX_LEN_FIELD.get(key, MAX_LEN)
    if not 0 < len(v) <= limit:
        return f"must be a non-empty string of at most {limit} characters, got {len(v)}"
    if any(bad_char(c) and not (key in MULTILINE and c in "\n\t") for c in v):
        return f"must be one line of printable text (no newline or control character), got {short(v)}"
    if key == "entry" and any(unicodedata.category(c) == "Cf" for c in v):  # zero-width, soft hyphen, LRM...
        return f"must hold no invisible or direction characters (Unicode Cf), got {ascii(v)[:80]}"
    return None


def _list_problem(key: str, v: list) -> str | None:
    if len(v) > MAX_ITEMS[key]:
        return f"at most {MAX_ITEMS[key]} entries, got {len(v)}"
    for item in v:
        problem = _text_problem(key, item) if isinstance(item, str) else f"entries must be strings, got {short(item)}"
        if problem:
            return problem
    return None


def _mapping_problem(v: dict) -> str | None:
    """Baseline / oracle overrides: at most 50 ``{parameter: scalar or short list of scalars}``."""
    scalar = (bool, int, float, str, type(None))
    if len(v) > 50:
        return f"at most 50 parameters, got {len(v)}"
    for k, x in v.items():
        if not (isinstance(k, str) and WORD_RE.fullmatch(k)):
            return f"parameter names are words ({WORD_RE.pattern}), got {short(k)}"
        items = x if isinstance(x, list) and len(x) <= 20 else [x]
        if not all(isinstance(i, scalar) and not (isinstance(i, str) and _text_problem("overrides", i))
                   for i in items):
            return f"{k!r}: a number, true/false, a one-line string or a list of at most 20 of these, got {short(x)}"
    return None


def _type_name(types: tuple) -> str:
    return " or ".join({str: "a string", int: "an integer", bool: "true/false", list: "a list",
                        dict: "a mapping"}[t] for t in types)


def validate_schema(path: Path, data) -> dict:
    """Field-level checks of a parsed submission.yaml; returns the data or raises SubmissionError."""
    if not isinstance(data, dict):
        raise SubmissionError(path, None, f"expected a mapping of fields, got {type(data).__name__}")
    for key in data:
        if key not in SCHEMA:
            raise SubmissionError(path, key if isinstance(key, str) else short(key),
                                  f"unknown field; valid fields: {', '.join(SCHEMA)}")
    kind = data.get("kind")
    if kind is None:
        raise SubmissionError(path, "kind", "missing (baseline | learned | oracle)")
    if kind not in KINDS:
        raise SubmissionError(path, "kind", f"{short(kind)} is not one of {', '.join(KINDS)}")
    for key, (types, required, desc) in SCHEMA.items():
        if key not in data or data[key] is None:
            if kind in required:
                raise SubmissionError(path, key, f"missing ({desc})")
            continue
        v = data[key]
        if not isinstance(v, types) or (int in types and isinstance(v, bool) and bool not in types):
            raise SubmissionError(path, key, f"must be {_type_name(types)}, got {short(v)}")
        bad = _text_problem(key, v) if isinstance(v, str) else _list_problem(key, v) if isinstance(v, list) \
            else _mapping_problem(v) if isinstance(v, dict) else None
        if bad:
            raise SubmissionError(path, key, bad)
    if name_problem(data["name"]):
        raise SubmissionError(path, "name", name_problem(data["name"]))
    if data["name"] != path.parent.name:
        raise SubmissionError(path, "name", f"{data['name']!r} differs from the directory name {short(path.parent.name)}")
    authors = data["authors"]
    if isinstance(authors, list) and not authors:
        raise SubmissionError(path, "authors", "must be a non-empty list of names")
    if "link" in data and link_problem(data["link"]):
        raise SubmissionError(path, "link", link_problem(data["link"]))
    if "seed" in data and problem(data["seed"], SEED_BOUNDS):
        raise SubmissionError(path, "seed", f"must lie {value_range(SEED_BOUNDS)}, got {short(data['seed'])}")
    for key, rx in (("encoder", WORD_RE), ("encoder_entry_points", WORD_RE), ("encoder_import", IMPORT_RE)):
        if key in data and not rx.fullmatch(data[key]):
            what = "is not of the form module:Class" if key == "encoder_import" else f"must match {rx.pattern}"
            raise SubmissionError(path, key, f"{short(data[key])} {what}")
    _check_privilege(path, data)
    if kind == "baseline" and data["policy"] not in BASELINE_POLICIES:
        raise SubmissionError(path, "policy", f"{short(data['policy'])} is not a baseline; valid: "
                                              f"{', '.join(BASELINE_POLICIES)}")
    if kind == "learned" and data.get("track", "v1") not in homes():
        raise SubmissionError(path, "track", f"{short(data['track'])} is not a track; valid: {', '.join(homes())}")
    if kind == "learned" and data["algo"] not in algo_names():
        raise SubmissionError(path, "algo", f"{short(data['algo'])} is not one of {', '.join(algo_names())}")
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


def _check_privilege(path: Path, data: dict) -> None:
    """The oracle and a value entry with the ``query`` lookahead read the humans' future: they must say so
    (``privileged: true``), and nothing else may."""
    kind, priv, look = data["kind"], data.get("privileged", False), data.get("lookahead")
    if look is not None and look not in LOOKAHEAD_MODELS:
        raise SubmissionError(path, "lookahead", f"{short(look)} is not one of {', '.join(LOOKAHEAD_MODELS)}")
    if look is not None and data.get("algo") != "value":
        raise SubmissionError(path, "lookahead", "only algo: value entries act by lookahead")
    if kind == "learned" and data.get("algo") == "value" and look is None:
        raise SubmissionError(path, "lookahead", f"an algo: value entry must name its lookahead model "
                                                 f"({' | '.join(LOOKAHEAD_MODELS)})")
    net = data.get("net")
    if net is not None and data.get("algo") != "value":
        raise SubmissionError(path, "net", "only algo: value entries name a value network")
    if kind == "learned" and data.get("algo") == "value" and net not in VALUE_NETS:
        raise SubmissionError(path, "net", f"an algo: value entry must name its value network, one of "
                                           f"{', '.join(VALUE_NETS)}; got {short(net)}")
    needs = kind == "oracle" or look in PRIVILEGED_MODELS
    if needs and priv is not True:
        why = "the oracle knows the humans' future" if kind == "oracle" else \
            f"lookahead {look} reads the humans' next states from the simulator"
        raise SubmissionError(path, "privileged", f"{why}: it must say privileged: true")
    if not needs and priv:
        raise SubmissionError(path, "privileged", "only the oracle and value entries with lookahead: "
                                                  f"{' | '.join(PRIVILEGED_MODELS)} are privileged")


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


class _Loader(yaml.SafeLoader):
    """``yaml.SafeLoader`` without aliases and anchors (a submission has no use for them, and a few hundred
    bytes of nested aliases expand to gigabytes) and without collections nested deeper than MAX_DEPTH."""

    def compose_node(self, parent, index):
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None):
            raise yaml.composer.ComposerError(None, None, "aliases and anchors (*x, &x) are not allowed",
                                              event.start_mark)
        self.depth = getattr(self, "depth", 0) + 1
        try:
            if self.depth > MAX_DEPTH:
                raise yaml.composer.ComposerError(None, None, f"nested deeper than {MAX_DEPTH} levels",
                                                  event.start_mark)
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


def load_yaml(path: Path):
    """The parsed ``submission.yaml`` at ``path``: a regular UTF-8 file of at most MAX_BYTES, no aliases."""
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise SubmissionError(path, None, "submission.yaml must be a regular file, not a symlink or a directory")
    if not path.is_file():
        raise SubmissionError(path, None, "missing submission.yaml")
    with path.open("rb") as f:
        raw = f.read(MAX_BYTES + 1)
    if len(raw) > MAX_BYTES:
        raise SubmissionError(path, None, f"larger than {MAX_BYTES} bytes")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise SubmissionError(path, None, f"not UTF-8 text (byte {e.start})") from None
    try:
        return yaml.load(text, Loader=_Loader)  # a SafeLoader
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e)
        raise SubmissionError(path, None, f"malformed YAML{where}: {problem}") from None
    except Exception as e:  # noqa: BLE001 - e.g. an integer of 50,000 digits: the file's problem, one line
        raise SubmissionError(path, None, f"malformed YAML: {type(e).__name__}: {e}") \
            from None


def inside(sub_dir: Path, rel: str, yaml_path: Path, fld: str) -> Path:
    """``sub_dir / rel`` if it lies inside ``sub_dir`` without a symlink on the way (it need not exist);
    else a SubmissionError naming ``fld``."""
    p = Path(rel)
    if not rel or p.is_absolute() or ".." in p.parts:
        raise SubmissionError(yaml_path, fld, f"{short(rel)} must be a relative path inside the submission "
                                              "directory (not absolute, no '..')")
    cur = sub_dir
    for part in p.parts:
        cur = cur / part
        if cur.is_symlink():
            raise SubmissionError(yaml_path, fld, f"{short(str(cur.relative_to(sub_dir)))} is a symlink: a "
                                                  "submission's files must lie inside the submission directory")
    if not cur.resolve().is_relative_to(sub_dir.resolve()):
        raise SubmissionError(yaml_path, fld, f"{short(rel)} is not inside the submission directory")
    return cur


def encoder_files(sub: Submission) -> list[Path]:
    """The file of ``sub``'s ``encoder_import`` module, found statically (never imported): ``pkg.mod`` is
    ``<dir>/pkg/mod.py`` or ``<dir>/pkg/mod/__init__.py``, inside the submission directory, no symlinks."""
    spec = sub.data.get("encoder_import")
    if not spec:
        return []
    mod = spec.partition(":")[0]
    rel = "/".join(mod.split("."))
    for candidate in (f"{rel}.py", f"{rel}/__init__.py"):
        path = inside(sub.dir, candidate, sub.yaml_path, "encoder_import")
        if path.is_file():
            return [path]
    raise SubmissionError(sub.yaml_path, "encoder_import", f"{mod!r} is not a module file inside the submission "
                                                           f"directory (expected {rel}.py or {rel}/__init__.py)")


def read_submission(sub_dir: Path) -> Submission:
    path = sub_dir / "submission.yaml"
    if name_problem(sub_dir.name):
        raise SubmissionError(path, "name", f"directory {name_problem(sub_dir.name)}")
    if sub_dir.is_symlink():
        raise SubmissionError(path, None, "the submission directory is a symlink: it must be a directory")
    data = validate_schema(path, load_yaml(path))
    # the row label as shown and compared: NFKC (a full-width or ligature form is its plain letters)
    sub = Submission(name=data["name"], dir=sub_dir, yaml_path=path, data=data, kind=data["kind"],
                     entry=unicodedata.normalize("NFKC", data.get("entry") or data["name"]))
    if sub.kind == "learned":
        sub.checkpoint = inside(sub_dir, data.get("checkpoint", "checkpoint.pt"), path, "checkpoint")
        if not sub.checkpoint.is_file():
            raise SubmissionError(path, "checkpoint", f"checkpoint file not found: {sub.checkpoint}")
        sub.extra_files = encoder_files(sub)
        for f, fld in [(sub.checkpoint, "checkpoint"), *((f, "encoder_import") for f in sub.extra_files)]:
            size = f.stat().st_size  # (before the fingerprint or a worker reads it)
            if size > MAX_FILE_BYTES:
                raise SubmissionError(path, fld, f"{f.name} is {size / 1024 ** 2:.0f} MB, more than "
                                                 f"{MAX_FILE_BYTES >> 20} MB")
    else:
        from crowdbench.leaderboard.overrides import override_problem

        bad = override_problem("oracle" if sub.kind == "oracle" else data["policy"], data.get("overrides") or {})
        if bad:
            raise SubmissionError(path, f"overrides.{bad[0]}", bad[1])
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
    sub_dir = Path(root) / "submissions" / str(name)
    data = {"name": name, "kind": "learned", "entry": entry, "encoder": cfg["encoder"]["name"],
            "algo": cfg["algo"]["name"], "seed": int(cfg["seed"]), "overrides": overrides, "authors": authors}
    track = trained_track(cfg)
    if data["algo"] == "value":  # the lookahead model it acts with; query reads the simulator: privileged
        data["lookahead"], data["net"] = cfg["algo"]["lookahead"], cfg["algo"]["net"]
        if data["lookahead"] in PRIVILEGED_MODELS:
            data["privileged"] = True
    for key, value in (("experiment", experiment), ("track", None if track == "v1" else track), ("link", link),
                       ("notes", notes)):
        if value:
            data[key] = value
    if name_problem(name):  # before anything is written: "../../x" or "/abs" would leave the leaderboard
        raise SubmissionError(Path(root) / "submissions", "name", name_problem(name))
    validate_schema(sub_dir / "submission.yaml", data)
    if sub_dir.exists() or sub_dir.is_symlink():
        raise SubmissionError(sub_dir, None, "already exists; remove it first to replace the submission")
    # built beside submissions/ and renamed into it whole: a kill leaves no half submission there
    build = pid_dir(Path(root) / ".building", "submit")
    try:
        keep = ("config", "actor", "frames", "updates", "wall_time_s")
        save_checkpoint(build / "checkpoint.pt", {k: state[k] for k in keep if k in state})
        (build / "submission.yaml").write_text(yaml.safe_dump(data, sort_keys=False, width=120))
        sub_dir.parent.mkdir(parents=True, exist_ok=True)
        os.rename(build, sub_dir)  # (refused if another submit made sub_dir meanwhile)
    except OSError as e:
        shutil.rmtree(build, ignore_errors=True)
        raise SubmissionError(sub_dir, None, f"cannot write it: {e.strerror or e} ({e.filename or build})") from None
    except BaseException:
        shutil.rmtree(build, ignore_errors=True)
        raise
    try:
        read_submission(sub_dir)
    except BaseException:  # a submission the harness would refuse is not left behind
        shutil.rmtree(sub_dir, ignore_errors=True)
        raise
    return sub_dir

