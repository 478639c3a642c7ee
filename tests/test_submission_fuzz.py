"""Fuzzing ``read_submission`` with seeded random and adversarial ``submission.yaml`` files.

Whatever the file holds (wrong types, huge strings, aliases, unknown fields, control characters, pipes,
``..`` and absolute paths, symlinks, deep nesting, binary garbage, an empty file, a directory named
submission.yaml, ...), ``read_submission`` returns or raises :class:`SubmissionError` with one line of
bounded length, quickly; the tables rendered from the accepted submissions keep their rows and columns.
A fixed seed and the standard library only (no hypothesis): every run tries the same cases.
"""

from __future__ import annotations

import os
import random
import re
import time
from pathlib import Path

import yaml

from crowdbench import policies
from crowdbench.envs.protocol import EVAL_SCENES
from crowdbench.leaderboard import SubmissionError, read_submission
from crowdbench.leaderboard.render import group_results, render_readme
from crowdbench.leaderboard.text import md
from crowdbench.leaderboard.track_tables import render_tracks
from crowdbench.leaderboard.tracks import TRACK_ORDER, TRACKS
from crowdbench.metric_table import IN_DOCS, IN_README, IN_TRACKS, in_table

SEED = 20261201
N_RANDOM = 250
MAX_MESSAGE = 500  # characters of a rejection line
MAX_CPU_S = 1.0  # CPU seconds of this process per case: a bound on work, whatever the machine's load

NASTY = ["Evil | World-best method | 1.000", "a\nb", "x\r\n| forged | 1 |", "<script>alert(1)</script>",
         "[click](javascript:alert(1))", "![img](http://x/y.png)", "`code`", "*bold* _it_ ~~s~~", "\\|",
         "\x00", "\x1b[31mred", "\u202eevil", "\u2028", "e\u0301", "名前", "🙂", "&#124;", "-->", "<!--",
         "../../etc/passwd", "/etc/passwd", "C:\\x", " ", "", "|", "||||", "#", "- item", "---"]
LINKS = ["https://ex.org/a", "http://ex.org", "javascript:alert(1)", "data:text/html,x", "https://", "ftp://x",
         "https://ex.org/a b", "//ex.org", "https://ex.org/|x", "https://[::1]/", "https://ex.org:99999/"]


def nasty_string(rng: random.Random) -> str:
    mode = rng.random()
    if mode < 0.4:
        return rng.choice(NASTY)
    if mode < 0.6:
        return "".join(rng.choice(NASTY) for _ in range(rng.randint(1, 5)))
    if mode < 0.8:  # random code points (surrogates excluded: they cannot be written as UTF-8)
        return "".join(chr(rng.choice([rng.randint(0, 0x7f), rng.randint(0x80, 0xd7ff), rng.randint(0xe000, 0x10ffff)]))
                       for _ in range(rng.randint(0, 40)))
    return rng.choice("ab|<_*`") * rng.choice([1, 199, 200, 201, 2001, 20_000])


def value(rng: random.Random, depth: int = 0):
    r = rng.random()
    if r < 0.3:
        return nasty_string(rng)
    if r < 0.45:
        return rng.choice([0, 1, -1, 2 ** 63, 2 ** 63 - 1, 10 ** 30, True, False, None, 1.5, float("inf"),
                           float("nan")])
    if r < 0.6 and depth < 12:
        return [value(rng, depth + 1) for _ in range(rng.randint(0, 4))]
    if r < 0.7 and depth < 12:
        return {nasty_string(rng)[:20] if rng.random() < 0.8 else rng.randint(0, 9): value(rng, depth + 1)
                for _ in range(rng.randint(0, 3))}
    if r < 0.8:
        return rng.choice(LINKS)
    return rng.choice(["orca", "straight", "learned", "baseline", "oracle", "td3", "mlp", "v1", "checkpoint.pt"])


def base(kind: str) -> dict:
    d = {"name": "fuzz", "kind": kind, "authors": ["a"]}
    return d | ({"policy": "orca"} if kind == "baseline" else {"encoder": "mlp", "algo": "td3"} if kind == "learned"
                else {"privileged": True})


def structured(rng: random.Random) -> dict:
    """A valid submission with a few fields replaced, added or removed."""
    data = base(rng.choice(["baseline", "learned", "oracle"]))
    for _ in range(rng.randint(0, 3)):
        op = rng.random()
        key = rng.choice(["name", "kind", "entry", "policy", "encoder", "encoder_import", "algo", "track",
                          "overrides", "authors", "link", "seed", "privileged", "checkpoint", "notes", "experiment",
                          "unknown_field", "encoder_entry_points"])
        if op < 0.15:
            data.pop(key, None)
        elif key in ("entry", "notes") and op < 0.6:
            data[key] = nasty_string(rng)
        elif key == "authors" and op < 0.6:
            data[key] = [nasty_string(rng) for _ in range(rng.randint(1, 3))]
        elif key == "link" and op < 0.7:
            data[key] = rng.choice(LINKS)
        else:
            data[key] = value(rng)
    return data


def dump(data: dict, rng: random.Random) -> bytes:
    try:
        text = yaml.safe_dump(data, allow_unicode=rng.random() < 0.5, width=rng.choice([80, 10 ** 6]))
    except yaml.YAMLError:
        text = repr(data)
    raw = text.encode("utf-8", "surrogatepass")
    r = rng.random()
    if r < 0.1:  # truncated
        raw = raw[:rng.randint(0, len(raw))]
    elif r < 0.2:  # a few flipped bytes
        b = bytearray(raw)
        for _ in range(rng.randint(1, 4)):
            if b:
                b[rng.randrange(len(b))] = rng.randrange(256)
        raw = bytes(b)
    return raw


LAUGHS = "a0: &a0 [x]\n" + "".join(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]\n" for i in range(1, 10))
ADVERSARIAL: list[tuple[str, bytes | None]] = [  # (description, file content; None: a special layout)
    ("empty file", b""), ("whitespace", b"  \n\n"), ("document marker", b"---\n"), ("null", b"~\n"),
    ("a list", b"- a\n- b\n"), ("a scalar", b"hello\n"), ("binary garbage", bytes(range(256)) * 8),
    ("NUL bytes", b"name: fuzz\x00\nkind: baseline\n"), ("latin-1", "name: f\xfczz\n".encode("latin-1")),
    ("BOM", b"\xef\xbb\xbfname: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\n"),
    ("billion laughs", (LAUGHS + "name: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\nseed: *a9\n").encode()),
    ("alias in authors", b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [&s " + b"x" * 10_000 + b", "
     + b", ".join([b"*s"] * 1000) + b"]\n"),
    ("merge key", b"base: &b {kind: baseline}\n<<: *b\nname: fuzz\n"),
    ("anchor only", b"name: &n fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\n"),
    ("deep list", b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\noverrides: " + b"[" * 30_000 + b"]" * 30_000),
    ("deep mapping", b"name: fuzz\nkind: baseline\nauthors: [a]\noverrides: " + b"{a: " * 5_000 + b"1" + b"}" * 5_000),
    ("over 64 kB", b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\nnotes: " + b"x" * 70_000 + b"\n"),
    ("huge int", b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\nseed: " + b"9" * 60_000 + b"\n"),
    ("python tag", b"name: !!python/object/apply:os.system [ls]\nkind: baseline\n"),
    ("binary tag", b"name: !!binary aGVsbG8=\nkind: baseline\n"), ("timestamp", b"name: 2001-12-14\nkind: baseline\n"),
    ("complex key", b"? [a, b]\n: c\nkind: baseline\n"), ("null key", b"~: x\nkind: baseline\n"),
    ("int key", b"1: x\nkind: baseline\n"), ("duplicate keys", b"name: fuzz\nname: other\nkind: baseline\n"),
    ("tabs", b"name:\tfuzz\n\tkind: baseline\n"), ("CRLF", b"name: fuzz\r\nkind: baseline\r\npolicy: orca\r\nauthors: [a]\r\n"),
    ("many authors", b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [" + b", ".join([b"a"] * 5000) + b"]\n"),
    ("many overrides", b"name: fuzz\nkind: learned\nencoder: mlp\nalgo: td3\nauthors: [a]\noverrides: ["
     + b", ".join([b"x=1"] * 5000) + b"]\n"),
    ("override int key", b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\noverrides: {1: 2}\n"),
    ("override nested", b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\noverrides: {safety_margin: {a: [1]}}\n"),
    ("checkpoint ..", b"name: fuzz\nkind: learned\nencoder: mlp\nalgo: td3\nauthors: [a]\ncheckpoint: ../x/checkpoint.pt\n"),
    ("checkpoint absolute", b"name: fuzz\nkind: learned\nencoder: mlp\nalgo: td3\nauthors: [a]\ncheckpoint: /etc/passwd\n"),
    ("checkpoint empty", b"name: fuzz\nkind: learned\nencoder: mlp\nalgo: td3\nauthors: [a]\ncheckpoint: ''\n"),
    ("checkpoint dir", b"name: fuzz\nkind: learned\nencoder: mlp\nalgo: td3\nauthors: [a]\ncheckpoint: .\n"),
    ("encoder_import os", b"name: fuzz\nkind: learned\nencoder: x\nalgo: td3\nauthors: [a]\nencoder_import: os:system\n"),
    ("encoder_import ..", b"name: fuzz\nkind: learned\nencoder: x\nalgo: td3\nauthors: [a]\nencoder_import: ../x:Y\n"),
    ("name ..", b"name: ..\nkind: baseline\npolicy: orca\nauthors: [a]\n"),
    ("name slash", b"name: a/b\nkind: baseline\npolicy: orca\nauthors: [a]\n"),
    ("link javascript", b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\nlink: javascript:alert(1)\n"),
    ("entry newline", b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\nentry: \"x\\n| y | 1 |\"\n"),
    ("directory named submission.yaml", None), ("symlinked submission.yaml", None), ("symlinked directory", None),
    ("symlinked checkpoint", None), ("missing submission.yaml", None), ("directory name with a newline", None),
]


def setup_case(root: Path, i: int, desc: str, raw: bytes | None) -> Path:
    """The submission directory of case ``i`` (named ``fuzz``: its yaml's name must equal it)."""
    parent = root / f"case{i}" / "submissions"
    d = parent / "fuzz"
    d.mkdir(parents=True)
    (d / "checkpoint.pt").write_bytes(b"never loaded by read_submission")
    if raw is not None:
        (d / "submission.yaml").write_bytes(raw)
        return d
    valid = b"name: fuzz\nkind: baseline\npolicy: orca\nauthors: [a]\n"
    if desc == "directory named submission.yaml":
        (d / "submission.yaml").mkdir()
    elif desc == "symlinked submission.yaml":
        (root / f"elsewhere{i}.yaml").write_bytes(valid)
        (d / "submission.yaml").symlink_to(root / f"elsewhere{i}.yaml")
    elif desc == "symlinked directory":
        real = root / f"real{i}" / "fuzz"
        real.mkdir(parents=True)
        (real / "submission.yaml").write_bytes(valid)
        (d / "checkpoint.pt").unlink()
        d.rmdir()
        d.symlink_to(real)
    elif desc == "symlinked checkpoint":
        (d / "checkpoint.pt").unlink()
        (root / f"outside{i}.pt").write_bytes(b"x")
        (d / "checkpoint.pt").symlink_to(root / f"outside{i}.pt")
        (d / "submission.yaml").write_bytes(b"name: fuzz\nkind: learned\nencoder: mlp\nalgo: td3\nauthors: [a]\n")
    elif desc == "directory name with a newline":
        d = parent / "fu\nzz | 1.000 |"
        d.mkdir()
        (d / "submission.yaml").write_bytes(valid.replace(b"fuzz", b'"fu\\nzz | 1.000 |"'))
    return d


def cases() -> list[tuple[str, bytes | None]]:
    rng = random.Random(SEED)
    out = list(ADVERSARIAL)
    for k in range(N_RANDOM):
        data = structured(rng) if rng.random() < 0.8 else {nasty_string(rng)[:10]: value(rng) for _ in range(3)}
        out.append((f"random {k}", dump(data, rng)))
    return out


def fake_result(sub) -> dict:
    """A results.json of ``sub`` (every metric 0.5 on every scene and CrowdNav setting)."""
    metrics = {m.key for table in (IN_README, IN_DOCS, IN_TRACKS) for m in in_table(table)}
    cell = {"mean": 0.5, "ci95": [0.4, 0.6], "n": 10}
    units = [*EVAL_SCENES, *(t.setting for t in TRACKS.values() if t.setting)]
    res = {"meta": {"submission": sub.name, "kind": sub.kind, "entry": sub.entry}, "submission": sub.data,
           "scenes": {s: {m: dict(cell) for m in metrics} for s in units}}
    if sub.kind == "oracle":
        res |= {"privileged": True, "unavoidable": {}}
    return res


def body_rows(text: str, heading: str) -> list[str]:
    section = text.split(heading, 1)[1].split("\n#", 1)[0]
    return [line for line in section.splitlines() if line.startswith("|")][2:]


def columns(line: str) -> int:
    return len(re.split(r"(?<!\\)\|", line)) - 2


def check_tables(text: str) -> None:
    """Every row of every table has its header's number of columns."""
    head = None
    for line in text.splitlines():
        if not line.startswith("|"):
            head = None
            continue
        head = columns(line) if head is None else head
        assert columns(line) == head, line


def test_read_submission_never_fails_otherwise(tmp_path):
    policies.default_config()  # compose the config once (not part of any case's time)
    t_all = time.process_time()
    accepted, failures = [], []
    for i, (desc, raw) in enumerate(cases()):
        d = setup_case(tmp_path, i, desc, raw)
        t = time.process_time()
        try:
            accepted.append((desc, read_submission(d)))
        except SubmissionError as e:
            msg = str(e)
            if "\n" in msg or len(msg) >= MAX_MESSAGE or not msg.startswith(str(d / "submission.yaml").split("\n")[0]):
                failures.append(f"{desc}: bad message {msg[:200]!r}")
        except Exception as e:  # noqa: BLE001 - collected and reported below
            failures.append(f"{desc}: {type(e).__name__}: {str(e)[:200]}")
        if time.process_time() - t > MAX_CPU_S:
            failures.append(f"{desc}: {time.process_time() - t:.2f} CPU s")
    assert not failures, "\n".join(failures[:20])
    assert time.process_time() - t_all < 20
    kinds = {s.kind for _, s in accepted}
    assert len(accepted) >= 40 and kinds == {"baseline", "learned", "oracle"}, (len(accepted), kinds)
    assert not any(desc in ("billion laughs", "alias in authors", "symlinked checkpoint") for desc, _ in accepted)

    # the accepted submissions, rendered: no submission text makes a row, a column, HTML or a link
    results = [fake_result(s) for _, s in accepted]
    groups = group_results(results)
    readme = render_readme(results, ["rejected: " + n for n in NASTY], list(EVAL_SCENES), None, [])
    check_tables(readme)
    assert len(body_rows(readme, "## Success rate")) == len(groups)
    assert len(body_rows(readme, "## Submissions")) == len(results)
    by_track = {t: results for t in TRACK_ORDER}
    tracks = render_tracks(by_track, list(EVAL_SCENES), None, [], ["rejected: " + n for n in NASTY])
    check_tables(tracks)
    home = [r for r in results if r["submission"].get("track", "v1") == "v1" or r["meta"]["kind"] != "learned"]
    assert len(body_rows(tracks, "## `v1`")) >= len(group_results(home))
    for text in (readme, tracks):
        assert not re.search(r"(?<!\\)<script|(?<!\\)\]\(javascript", text) and "\x00" not in text


def test_md_escapes_every_random_string():
    rng = random.Random(SEED)
    for _ in range(2000):
        s = nasty_string(rng)
        out = md(s)
        assert "\n" not in out and "\r" not in out and columns(f"| {out} |") == 1, (s, out)
        assert not re.search(r"(?<!\\)[<>\[\]`*]", out), (s, out)
    assert md("MP-GatedGCN-RL (TD3, gatedgcn, uniform replay, 143k frames)") == \
        "MP-GatedGCN-RL (TD3, gatedgcn, uniform replay, 143k frames)"
    assert md("gatedgcn_td3_s0") == "gatedgcn_td3_s0" and md("_x_") == r"\_x\_"
    assert os.path.sep == "/"  # the cases' paths
