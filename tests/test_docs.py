"""The documentation a user reads: no work-period dating, no dead links, no paths that do not exist."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

# A numbered period of work: "session 3", "sessions 6-7", "session-7", "session_2", "(session 2)",
# "sprint 4", "stop 12", "iteration 5 of the work". Not "sessionmaker", "a Hydra session", "stop
# after 30 minutes" or "stop 30 s later" (a number followed by a unit is a quantity, not a period).
UNITS = r"(?:s|ms|min|minutes?|seconds?|hours?|h|frames?|steps?|episodes?|updates?|%|m\b)"
WORK_PERIOD = re.compile(
    r"\b(?:sessions?|sprints?)[ _-]?\d+"
    r"|\bstop[ _-]\d+\b(?![ .,]?\d)(?!\s*" + UNITS + r")"
    r"|\biterations?[ _-]\d+ of the (?:work|project)",
    re.IGNORECASE,
)
EXEMPT = {"CHANGELOG.md", "tests/test_docs.py"}  # the history lives there, dated; this file holds samples


def tracked_files() -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [f for f in out.stdout.decode().split("\0") if f]


def text_of(path: Path) -> str | None:
    """The file's text, or None for binary files (a NUL byte or not UTF-8)."""
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


@pytest.mark.parametrize("sample", [
    "session 3", "Sessions 6-7", "session-7", "session_2", "(session 2)", "sprint 4", "stop 12",
    "iteration 5 of the work", "session2",
])
def test_the_work_period_pattern_catches(sample):
    assert WORK_PERIOD.search(sample)


@pytest.mark.parametrize("sample", [
    "sessionmaker", "a Hydra session", "the session's output", "stop after 30 minutes",
    "stop 30 s later", "stops", "iteration over the scenes", "sessions of Ray",
])
def test_the_work_period_pattern_spares(sample):
    assert not WORK_PERIOD.search(sample)


def test_no_tracked_file_dates_its_content_by_a_work_period():
    hits = []
    for name in tracked_files():
        path = ROOT / name
        if name in EXEMPT or not path.is_file():
            continue
        text = text_of(path)
        if text is None:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            m = WORK_PERIOD.search(line)
            if m:
                hits.append(f"{name}:{n}: {m.group(0)!r}: {line.strip()[:120]}")
    assert not hits, "work periods in tracked files (say what and why, not when):\n" + "\n".join(hits)


LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)|!\[[^\]]*\]\(([^)\s]+)\)")


def headings_anchors(md: Path) -> set[str]:
    """GitHub's anchors of the headings of a markdown file."""
    anchors, in_code = set(), False
    for line in md.read_text().splitlines():
        if line.startswith("```"):
            in_code = not in_code
        if in_code or not line.startswith("#"):
            continue
        title = line.lstrip("#").strip().lower()
        slug = re.sub(r"[^\w\- ]", "", title).replace(" ", "-")
        n, base = 1, slug
        while slug in anchors:
            slug, n = f"{base}-{n}", n + 1
        anchors.add(slug)
    return anchors


def strip_code_blocks(text: str) -> str:
    return re.sub(r"^```.*?^```", "", text, flags=re.MULTILINE | re.DOTALL)


@pytest.mark.parametrize("md", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(md):
    bad = []
    for m in LINK.finditer(strip_code_blocks(md.read_text())):
        target = m.group(1) or m.group(2)
        if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        dest = (md.parent / file_part).resolve() if file_part else md
        if not dest.exists():
            bad.append(f"{target}: no file {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest}")
        elif anchor and dest.suffix == ".md" and anchor not in headings_anchors(dest):
            bad.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert not bad, f"{md.relative_to(ROOT)}: dead links:\n" + "\n".join(bad)


# paths that name what a command writes, not files of the repository
OUTPUT_PREFIXES = ("outputs/", "OUT/", "RUN/", "DIR/", "SWEEP_DIR/", "runs/")
PATH = re.compile(r"(?<![\w./-])((?:crowdbench|docs|benchmarks)/[\w./*{},-]*[\w*}])")


GYM_ID = re.compile(r"^crowdbench/\w+-v\d+$")  # a Gymnasium env id (crowdbench/CrowdNav-v0), not a path


def mentioned_paths(text: str) -> set[str]:
    return {m.group(1) for m in PATH.finditer(text) if not GYM_ID.match(m.group(1))}


def expand(path: str) -> list[str]:
    """``a/{b,c}.py`` and ``a/b|c`` forms as the concrete paths they name."""
    m = re.search(r"\{([^}]*)\}", path)
    if m:
        return [q for alt in m.group(1).split(",") for q in expand(path[:m.start()] + alt + path[m.end():])]
    return [path]


@pytest.mark.parametrize("md", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_mentioned_repository_paths_exist(md):
    missing = []
    for path in sorted(mentioned_paths(md.read_text())):
        if path.startswith(OUTPUT_PREFIXES):
            continue
        for p in expand(path):
            p = p.rstrip(".")
            if "*" in p:
                if not list(ROOT.glob(p)):
                    missing.append(p)
            elif not (ROOT / p).exists():
                missing.append(p)
    assert not missing, f"{md.relative_to(ROOT)} names paths that do not exist: {', '.join(missing)}"


def test_the_path_pattern():
    text = "see `crowdbench/conf/algo/td3.yaml`, docs/guide.md#sweeps and benchmarks/bench_env.py."
    assert mentioned_paths(text) == {"crowdbench/conf/algo/td3.yaml", "docs/guide.md", "benchmarks/bench_env.py"}
    assert mentioned_paths("import crowdbench.envs; leaderboard/crowdbench/x") == set()
    assert expand("crowdbench/{a,b}.py") == ["crowdbench/a.py", "crowdbench/b.py"]
