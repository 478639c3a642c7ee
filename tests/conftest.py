"""Shared test set-up: the quick/full split and the system packages some tests need.

``pytest`` runs the quick suite; ``pytest --full`` (what CI runs) adds the tests marked ``slow``.
A test that needs a system program (bubblewrap, Chromium) skips with the package to install, except
where ``CROWDBENCH_REQUIRE_SYSTEM=1`` (set by ``.ci/run``, which installs them): there the skip is a
failure, so CI never passes by silently skipping them.
"""

from __future__ import annotations

import json
import os
import shutil
from collections import defaultdict
from pathlib import Path

import pytest

# seconds per test of a recent run (`pytest --full --store-durations`): the suite starts the longest first
DURATIONS = Path(__file__).with_name("durations.json")

# pytest-xdist runs one test process per core (pyproject's addopts): a torch thread pool in each would
# oversubscribe the cores, and OpenMP's spinning threads then slow every test several-fold
if os.environ.get("PYTEST_XDIST_WORKER"):
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")

SYSTEM = {  # program -> (Debian package, install command)
    "bwrap": ("bubblewrap", "apt-get install bubblewrap"),
    "chromium": ("chromium", "apt-get install chromium chromium-driver"),
    "chromedriver": ("chromium-driver", "apt-get install chromium chromium-driver"),
    "ffmpeg": ("ffmpeg", "apt-get install ffmpeg"),
    "ffprobe": ("ffmpeg", "apt-get install ffmpeg"),
}


def pytest_addoption(parser):
    parser.addoption("--full", action="store_true", help="also run the tests marked slow (what CI runs)")
    parser.addoption("--store-durations", action="store_true",
                     help=f"record each test's seconds in {DURATIONS.name} (read to start the longest first)")


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: part of the full suite only (`pytest --full`, CI)")


def pytest_collection_modifyitems(config, items):
    if not config.getoption("--full"):
        slow = [i for i in items if i.get_closest_marker("slow")]
        if slow:
            config.hook.pytest_deselected(items=slow)
            items[:] = [i for i in items if not i.get_closest_marker("slow")]
    longest_first(items)


def longest_first(items) -> None:
    """Order the test files by their recorded seconds, longest first, each file's tests in their own order.
    Why: pytest-xdist hands the tests to its workers in this order, so a long file started last would run
    alone on one core while the other idles. Files stay whole so that a module-scoped fixture is built
    once per worker, as in file order; files without a record come last (the sort is stable)."""
    known = json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}
    weight: dict[str, float] = defaultdict(float)
    for item in items:
        weight[item.nodeid.split("::")[0]] += known.get(item.nodeid, 0.0)
    items.sort(key=lambda i: -weight[i.nodeid.split("::")[0]])


_SECONDS: dict[str, float] = defaultdict(float)


def pytest_runtest_logreport(report):
    _SECONDS[report.nodeid] += report.duration  # setup + call + teardown


def pytest_sessionfinish(session):
    if not session.config.getoption("--store-durations") or hasattr(session.config, "workerinput"):
        return  # the xdist controller writes what its workers reported
    known = json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}
    # tests under half a second do not change the order: kept out, the file stays short
    known = {k: v for k, v in known.items() if k not in _SECONDS}
    known.update({k: round(v, 2) for k, v in _SECONDS.items() if v >= 0.5})
    DURATIONS.write_text(json.dumps(dict(sorted(known.items())), indent=0) + "\n")


def require_system(program: str, available: bool | None = None) -> None:
    """Skip (or, under ``CROWDBENCH_REQUIRE_SYSTEM=1``, fail) unless ``program`` is usable here.
    ``available`` overrides the PATH look-up for programs that can be installed yet unusable
    (bubblewrap without user namespaces)."""
    ok = shutil.which(program) is not None if available is None else available
    if ok:
        return
    package, install = SYSTEM[program]
    msg = f"needs {program} from the Debian package {package} ({install})"
    if os.environ.get("CROWDBENCH_REQUIRE_SYSTEM") == "1":
        pytest.fail(f"{msg}; CROWDBENCH_REQUIRE_SYSTEM=1 forbids skipping it")
    pytest.skip(msg)
