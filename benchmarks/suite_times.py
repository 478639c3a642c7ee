"""Wall time of the test suite and the time of each test file (summed over its tests).

    python benchmarks/suite_times.py                 # the quick suite (`pytest`), both cores
    python benchmarks/suite_times.py --full          # the whole suite (`pytest --full`, what CI runs)
    python benchmarks/suite_times.py --load A.xml    # the per-file table of an earlier run's JUnit report

Per-file times are the sum of the file's test durations (setup, call and teardown, as JUnit reports
them), so with two workers they add up to about twice the wall time. Run it with nothing else running.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def per_file(report: Path) -> dict[str, tuple[float, int]]:
    """JUnit report -> {test file: (seconds, tests)}."""
    out: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    for case in ET.parse(report).getroot().iter("testcase"):
        # classname is tests.test_x (or tests.test_x.TestClass): the file is its second part
        parts = case.get("classname", "").split(".")
        name = (parts[1] if len(parts) > 1 else parts[0]) + ".py"
        out[name][0] += float(case.get("time", 0.0))
        out[name][1] += 1
    return {k: (v[0], int(v[1])) for k, v in out.items()}


def table(times: dict[str, tuple[float, int]], top: int) -> str:
    rows = sorted(times.items(), key=lambda kv: -kv[1][0])
    lines = ["| file | tests | seconds |", "|---|---|---|"]
    lines += [f"| {f} | {n} | {s:.1f} |" for f, (s, n) in rows[:top]]
    rest = rows[top:]
    if rest:
        lines.append(f"| {len(rest)} other files | {sum(n for _, (_, n) in rest)} | "
                     f"{sum(s for _, (s, _) in rest):.1f} |")
    lines.append(f"| **all** | {sum(n for _, (_, n) in rows)} | {sum(s for _, (s, _) in rows):.1f} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--full", action="store_true", help="the whole suite (pytest --full)")
    ap.add_argument("--load", type=Path, help="a JUnit XML report of an earlier run")
    ap.add_argument("--top", type=int, default=15, help="files listed (the rest in one row)")
    ap.add_argument("pytest_args", nargs="*", help="passed to pytest (after --)")
    args = ap.parse_args()
    report = args.load
    if report is None:
        report = Path(tempfile.mkdtemp()) / "report.xml"
        cmd = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", f"--junitxml={report}",
               *(["--full"] if args.full else []), *args.pytest_args]
        t = time.perf_counter()
        rc = subprocess.run(cmd, cwd=ROOT, check=False).returncode
        wall = time.perf_counter() - t
        print(f"\n{' '.join(cmd[2:])}: exit {rc}, wall time {wall / 60:.1f} min ({wall:.0f} s); report {report}")
    print(table(per_file(report), args.top))
    return 0


if __name__ == "__main__":
    sys.exit(main())
