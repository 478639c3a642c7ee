"""Fuzzing the harness's trust boundary with a fixed seed and a time bound: garbage on the pipe,
adversarial replies from a worker, random and broken checkpoints. The harness must never crash,
never hang, and never change another submission's result (straight-to-goal's, byte for byte)."""

from __future__ import annotations

import json
import os
import random
import struct
import sys
import time
from pathlib import Path

import pytest
import torch

from crowdbench.leaderboard import run, wire
from crowdbench.leaderboard.loading import dummy_obs
from crowdbench.leaderboard.sandbox import Limits
from crowdbench.leaderboard.worker import WorkerError, WorkerPolicy

SEED = 20261201


def _frame(rng: random.Random) -> bytes:
    """One adversarial message: random bytes, lying lengths, malformed headers or array specs."""
    kind = rng.randrange(7)
    if kind == 0:
        return rng.randbytes(rng.randrange(0, 64))
    if kind == 1:  # lengths far beyond the bounds
        return struct.pack(">II", rng.choice([wire.MAX_HEADER + 1, 2 ** 32 - 1]), rng.randrange(2 ** 32))
    heads = [b"not json", b"[1, 2]", b'{"op": 3}', b'{"op": "action", "arrays": 7}',
             b'{"op": "action", "arrays": [["action", "float64", [1, 1, 2]]]}',
             b'{"op": "action", "arrays": [["action", "float32", [-1, 1, 2]]]}',
             b'{"op": "action", "arrays": [["action", "float32", [4, 1, 2]]]}',
             b'{"op": "action", "arrays": [["action", "float32", [4, 1, 2], 9]]}',
             '{"op": "\u00e9\ud800"}'.encode("utf-8", "surrogatepass"), b'{"op": "action", "arrays": [[1, 2, 3]]}']
    head = rng.choice(heads)
    payload = rng.randbytes(rng.choice([0, 8, 31, 32, 33, 64]))
    data = struct.pack(">II", len(head), len(payload)) + head + payload
    return data[:rng.randrange(len(data) + 1)] if kind == 6 else data


def test_wire_reader_survives_garbage():
    rng = random.Random(SEED)
    t0 = time.process_time()
    for _ in range(300):
        r, w = os.pipe()
        os.write(w, _frame(rng))
        os.close(w)
        try:
            header, arrays = wire.recv(r, time.monotonic() + 1.0, max_payload=32)
            assert isinstance(header, dict) and all(a.nbytes <= 32 for a in arrays.values())
        except (wire.WireError, TimeoutError):
            pass
        finally:
            os.close(r)
    r, w = os.pipe()  # a peer that never writes costs the deadline, not more
    t = time.process_time()
    with pytest.raises(TimeoutError):
        wire.recv(r, time.monotonic() + 0.3)
    assert time.process_time() - t < 0.2  # waited in select, not in a busy loop
    os.close(r), os.close(w)
    assert time.process_time() - t0 < 20  # CPU seconds: a bound on work


FAKE_WORKER = '''
import os, random, struct, sys, json
sys.path.insert(0, {here!r})
seed = int(os.environ["FUZZ_CASE"])
rng = random.Random(seed)
def frame(head, payload=b""):
    head = json.dumps(head).encode()
    os.write(1, struct.pack(">II", len(head), len(payload)) + head + payload)
def read():
    n_h, n_p = struct.unpack(">II", os.read(0, 8))
    got = b""
    while len(got) < n_h + n_p:
        got += os.read(0, n_h + n_p - len(got))
    return json.loads(got[:n_h])
read()
frame({{"op": "ready", "frame": rng.choice(["rotate", "rotate", "polar", 7])}})
while True:
    h = read()
    if h["op"] == "reset":
        frame({{"op": "ok"}})
        continue
    b = h["arrays"][0][2][0]
    choice = rng.randrange(8)
    if choice == 0:
        frame({{"op": "action", "arrays": [["action", "float32", [b, 1, 2]]]}}, struct.pack("<f", float("nan")) * 2 * b)
    elif choice == 1:
        frame({{"op": "action", "arrays": [["action", "float32", [b, 1, 3]]]}}, b"\\0" * 12 * b)
    elif choice == 2:
        frame({{"op": "action", "arrays": [["action", "bool", [b, 1, 2]]]}}, b"\\1" * 2 * b)
    elif choice == 3:
        frame({{"op": "error", "message": "x" * 10000}})
    elif choice == 4:
        os.write(1, rng.randbytes(rng.randrange(1, 100)))
    elif choice == 5:
        sys.exit(rng.randrange(256))
    elif choice == 6:
        frame({{"op": "action", "arrays": [["action", "float32", [b, 1, 2]]]}}, struct.pack("<f", 0.5) * 2 * b)
    else:
        import time
        time.sleep(30)
'''


@pytest.mark.slow
def test_adversarial_worker_replies_are_one_line_rejections(tmp_path, monkeypatch):
    """A worker that answers with NaN, wrong shapes or dtypes, garbage, a flood, an exit or silence."""
    script = tmp_path / "fake_worker.py"
    script.write_text(FAKE_WORKER.format(here=str(tmp_path)))
    import crowdbench.leaderboard.worker as worker_mod

    monkeypatch.setattr(worker_mod, "command", lambda scratch, limits: [sys.executable, str(script)])
    monkeypatch.setattr(worker_mod, "environment", lambda scratch: {**os.environ, "PYTHONPATH": ""})
    obs = dummy_obs(batch=4)
    outcomes = set()  # each case's wall time is bounded by its Limits (step 0.5 s, load 10 s), not asserted
    for case in range(40):
        monkeypatch.setenv("FUZZ_CASE", str(case))
        try:
            with WorkerPolicy(tmp_path, f"fuzz{case}", Limits(step_s=0.5, load_s=10)) as p:
                p.reset(torch.ones(4, dtype=torch.bool))
                for _ in range(3):
                    a = p.act(obs)
                    assert a.shape == (4, 1, 2) and torch.isfinite(a).all()
                outcomes.add("ok")
        except WorkerError as e:
            msg = str(e)
            assert "\n" not in msg and len(msg) <= 240, msg
            outcomes.add(msg.split(" at step")[0].split(" within")[0][:40])
    assert len(outcomes) >= 5, outcomes  # the generator reached many different failure modes


def _random_checkpoint(rng: random.Random, path: Path, real: bytes) -> None:
    from crowdbench.algos.checkpoint import save_checkpoint

    kind = rng.randrange(6)
    if kind == 0:
        path.write_bytes(rng.randbytes(rng.randrange(1, 2048)))
        return
    if kind == 1:
        path.write_bytes(real[:rng.randrange(1, len(real))])
        return
    state = torch.load(_REAL, weights_only=True)
    cfg = state["config"]
    if kind == 2:  # wrong types and values in the config
        key = rng.choice(["v_max", "frame"])
        cfg["env"][key] = rng.choice(["fast", "polar", None, -1.0, [1, 2], float("inf")])
    elif kind == 3:  # weights of random scale, NaN or inf
        name = rng.choice(sorted(state["actor"]))
        state["actor"][name] = state["actor"][name] * rng.choice([float("nan"), float("inf"), 3e38, -3e38, 0.0])
    elif kind == 4:  # an encoder size that would need far more memory than the limit
        cfg["encoder"]["dim"] = rng.choice([10 ** 6, 2 ** 31, -3, 0])
    else:  # weights that do not fit
        name = rng.choice(sorted(state["actor"]))
        state["actor"][name] = torch.randn(rng.randrange(1, 5), rng.randrange(1, 5))
    save_checkpoint(path, state)


_REAL = Path(__file__).resolve().parents[1] / "leaderboard" / "submissions" / "mlp_td3_s0" / "checkpoint.pt"


def _not_json(constant: str):
    raise AssertionError(f"{constant} in results.json (not strict JSON)")


@pytest.mark.slow
def test_random_checkpoints_never_change_another_row(tmp_path):
    rng = random.Random(SEED)
    real = _REAL.read_bytes()
    fast = {"episodes": 3, "scenes": ["hotel"], "tracks": ["v1"]}

    def straight(root: Path) -> None:
        d = root / "submissions" / "straight"
        d.mkdir(parents=True)
        (d / "submission.yaml").write_text("name: straight\nkind: baseline\nentry: Straight\npolicy: straight\n"
                                           "authors: [a]\n")

    clean = tmp_path / "clean"
    straight(clean)
    assert run(clean, log=lambda m: None, **fast) == 0
    root = tmp_path / "fuzz"
    straight(root)
    names = [f"ckpt{i}" for i in range(8)]
    for name in names:
        d = root / "submissions" / name
        d.mkdir(parents=True)
        (d / "submission.yaml").write_text(f"name: {name}\nkind: learned\nencoder: mlp\nalgo: td3\nauthors: [a]\n")
        _random_checkpoint(rng, d / "checkpoint.pt", real)
    log: list[str] = []
    rc = run(root, log=log.append, limits=Limits(step_s=20, load_s=120, memory_gb=6), **fast)
    assert rc in (0, 1)
    errors = [m for m in log if "error" in m]
    for name in names:
        mine = [m for m in errors if f"submissions/{name}/" in m]
        evaluated = (root / "results" / name / "results.json").is_file()
        assert evaluated != bool(mine), (name, mine)
        assert all("\n" not in m and len(m) < 600 for m in mine)
        if evaluated:  # a checkpoint that still acts: finite numbers, strict JSON
            json.loads((root / "results" / name / "results.json").read_text(), parse_constant=_not_json)
    assert (root / "results" / "straight" / "results.json").read_text() == \
        (clean / "results" / "straight" / "results.json").read_text()
    assert (root / "README.md").is_file()
