"""Hostile workers, fuzzed with a fixed seed and bounded work (issue 37): each draws a combination of
attacks (a host Unix socket, temp floods, forks, sleeping, crashing) and some submissions play label
tricks (another row's entry, with lookalike letters, invisible characters, case). Afterwards the
straight-to-goal and ORCA results and rows are byte-identical to a run without them, nothing reached
the host's socket, and the table is written."""

from __future__ import annotations

import random

import pytest
from conftest import require_system

from crowdbench.leaderboard import run
from crowdbench.leaderboard.sandbox import Limits, bubblewrap
from tests.test_budget import rows
from tests.test_confinement import Listener
from tests.test_entries import add_orca, learned
from tests.test_isolation import ENCODER, add_straight, make_learned

SEED = 20261203
FAST = {"episodes": 3, "scenes": ["hotel"], "tracks": ["v1"]}
WORKERS, LABELS = 3, 5  # hostile submissions with code, and with label tricks only (no worker)

ATTACKS = {
    "socket": '''
import socket
try:
    s = socket.socket(socket.AF_UNIX); s.settimeout(2); s.connect({sock!r}); s.sendall(b"leak")
except OSError:
    pass
''',
    "flood": '''
import os
for where in ({where!r}, "/dev/shm"):
    try:
        for n in range({files}):
            with open(os.path.join(where, f"f{{n}}"), "wb") as f:
                f.write(b"x" * ({mb} << 20))
    except OSError:
        pass
''',
    "fork": '''
import os
for _ in range({n}):
    try:
        if os.fork() == 0:
            os._exit(0)
    except OSError:
        break
''',
    "sleep": '''
import time
_f = Enc.forward
def _slow(self, robot, *a, **k):
    if robot.shape[0] > 2:
        time.sleep({s})
    return _f(self, robot, *a, **k)
Enc.forward = _slow
''',
    "crash": "raise RuntimeError('crash')\n",
}
TRICKS = ["\u200b", "\u00ad", "\u200e", "\u043e", "case", "same"]


REQUIRED = ["socket", "flood", "fork", "sleep"]  # spread over the workers: every kind is tried


def hostile_code(rng: random.Random, sock: str, i: int) -> str:
    picks = list(dict.fromkeys(REQUIRED[i::WORKERS] + rng.sample(sorted(ATTACKS), rng.randint(0, 2))))
    if "crash" in picks:  # last: the other attacks run first
        picks = [p for p in picks if p != "crash"] + ["crash"]
    params = {"sock": sock, "where": rng.choice(["/tmp", "/var/tmp", "/run"]), "files": rng.randint(1, 40),
              "mb": rng.choice([1, 4]), "n": rng.randint(1, 50), "s": rng.choice([0.3, 0.6])}
    return "".join(ATTACKS[p].format(**params) for p in picks)


def trick(rng: random.Random, label: str) -> str:
    t = rng.choice(TRICKS)
    if t == "case":
        return label.swapcase()
    if t == "same":
        return label
    if t == "\u043e":
        return label.replace("o", t, 1)
    i = rng.randrange(1, len(label))
    return label[:i] + t + label[i:]


@pytest.mark.slow
def test_hostile_workers_and_label_tricks_leave_straight_and_orca_identical(tmp_path):
    require_system("bwrap", bubblewrap() is not None)
    rng = random.Random(SEED)
    lim = Limits(step_s=10.0, load_s=120.0, memory_gb=6.0, scratch_mb=16, sandbox="bubblewrap",
                 budget_factor=20.0, budget_floor_s=6.0)
    clean = tmp_path / "clean"
    add_straight(clean)
    add_orca(clean)
    assert run(clean, log=lambda m: None, limits=lim, **FAST) == 0

    root = tmp_path / "lb"
    add_straight(root)
    add_orca(root)
    listener = Listener(tmp_path / "host.sock")
    try:
        for i in range(WORKERS):
            make_learned(root, f"h{i}", ENCODER + hostile_code(rng, str(tmp_path / "host.sock"), i))
        for i in range(LABELS):
            label = trick(rng, rng.choice(["Straight to goal", "ORCA"]))
            learned(root, f"t{i}", label, encoder=rng.choice(["mlp", "gcn"]), seed=i)
        log: list[str] = []
        code = run(root, log=log.append, limits=lim, **FAST)
    finally:
        listener.close()
    assert listener.got == []
    errors = [m for m in log if "error" in m]
    assert code == 1 and all("\n" not in m and len(m) < 500 for m in errors)
    for i in range(LABELS):  # every label trick is refused (schema: Cf characters; entries.py: the rest)
        assert any(f"submissions/t{i}/" in m and "field 'entry'" in m for m in errors), (i, errors)
    for name in ("straight", "orca"):
        assert (root / "results" / name / "results.json").read_bytes() == \
            (clean / "results" / name / "results.json").read_bytes(), name
    assert rows((root / "README.md").read_text()) == rows((clean / "README.md").read_text()) != []
