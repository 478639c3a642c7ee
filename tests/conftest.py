"""Shared test set-up: the quick/full split and the system packages some tests need.

``pytest`` runs the quick suite; ``pytest --full`` (what CI runs) adds the tests marked ``slow``.
A test that needs a system program (bubblewrap, Chromium) skips with the package to install, except
where ``CROWDBENCH_REQUIRE_SYSTEM=1`` (set by ``.ci/run``, which installs them): there the skip is a
failure, so CI never passes by silently skipping them.
"""

from __future__ import annotations

import os
import shutil

import pytest

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


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: part of the full suite only (`pytest --full`, CI)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--full"):
        return
    slow = [i for i in items if i.get_closest_marker("slow")]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [i for i in items if not i.get_closest_marker("slow")]


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
