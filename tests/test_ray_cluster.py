"""The Ray cluster recipe of docs/guide.md (section "A Ray cluster"), run as written on two nodes of this
machine: a head and a second node, token authentication, a 2-run sweep and the leaderboard fan-out, each
spread over both nodes (shown by the cluster's own task records, as ``ray list tasks`` shows them)."""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_sweep import TINY

pytestmark = pytest.mark.slow

# `ray` of this interpreter (its workers then import this crowdbench), whatever `ray` is first on PATH
RAY = [sys.executable, "-m", "ray.scripts.scripts"]
LEADERBOARD_FAST = ["--tracks", "v1", "--episodes", "1", "--scenes", "hotel", "--sandbox", "none"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cluster_env(tmp: Path) -> dict:
    """The recipe's environment: token authentication with one token shared by every node and client
    (passed in the environment, so that no ~/.ray/auth_token is written); Ray's session files in
    ``tmp`` so that other Ray clusters on this machine are neither joined nor disturbed."""
    return {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32),
            "OMP_NUM_THREADS": "1", "RAY_USAGE_STATS_ENABLED": "0", "RAY_TMPDIR": str(tmp)}


def start_node(args: list[str], env: dict, log: Path) -> subprocess.Popen:
    """``ray start ... --block`` in its own process group: the test owns every process the node starts and
    stops exactly those (``ray stop`` would stop every Ray process of this user on the machine)."""
    out = log.open("w")
    return subprocess.Popen([*RAY, "start", *args, "--block", "--disable-usage-stats"], env=env, stdout=out,
                            stderr=subprocess.STDOUT, start_new_session=True)


def stop_node(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)  # `ray start --block` stops its node's processes on SIGTERM
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)  # anything of the group still alive
    except ProcessLookupError:
        pass


def nodes_of_tasks(address: str, env: dict, name: str) -> set[str]:
    """Node ids that ran tasks called ``name`` (the cluster's task records in its GCS)."""
    code = ("import ray, sys\n"
            f"ray.init(address={address!r}, logging_level='ERROR')\n"
            "from ray._private.state import state\n"
            "for e in state._get_all_task_events():\n"
            f"    if e.task_info.name == {name!r} and e.state_updates.node_id:\n"
            "        print(e.state_updates.node_id.hex())\n")
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120,
                       check=False)
    assert p.returncode == 0, p.stderr[-2000:]
    return set(p.stdout.split())


def wait_for_nodes(address: str, env: dict, n: int) -> None:
    for _ in range(60):
        p = subprocess.run([*RAY, "status", f"--address={address}"], env=env, capture_output=True, text=True,
                           check=False)
        if p.returncode == 0 and p.stdout.count(" node_") >= n:
            return
        time.sleep(1)
    pytest.fail(f"the cluster at {address} did not reach {n} nodes: {p.stdout[-1000:]} {p.stderr[-1000:]}")


def crowdbench(args: list[str], env: dict, cwd: Path) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, "-m", "crowdbench.entry", *args], env=env, cwd=cwd, capture_output=True,
                       text=True, timeout=600, check=False)
    assert p.returncode == 0, f"crowdbench {' '.join(args)}: {p.stdout[-2000:]} {p.stderr[-3000:]}"
    return p


def test_two_node_cluster_runs_a_sweep_and_the_leaderboard_on_both_nodes(tmp_path):
    ray_tmp = Path(f"/tmp/cb{os.getpid()}")  # Ray's socket paths must stay short: not under pytest's tmp_path
    env = cluster_env(ray_tmp)
    port = free_port()
    address = f"127.0.0.1:{port}"
    head = start_node(["--head", f"--port={port}", "--node-ip-address=127.0.0.1", "--num-cpus=1",
                       f"--temp-dir={ray_tmp}", "--include-dashboard=false",
                       f"--ray-client-server-port={free_port()}", f"--dashboard-agent-listen-port={free_port()}"],
                      env, tmp_path / "head.log")
    nodes, t0 = [head], time.time()
    phase = {}
    try:
        wait_for_nodes(address, env, 1)
        nodes.append(start_node([f"--address={address}", "--node-ip-address=127.0.0.1", "--num-cpus=1",
                                 f"--dashboard-agent-listen-port={free_port()}"], env, tmp_path / "node2.log"))
        wait_for_nodes(address, env, 2)
        phase["cluster"] = time.time() - t0
        crowdbench(["run", "-m", "seed=0,1", *TINY, "out=sweep", "hydra/launcher=ray",
                    f"hydra.launcher.ray.init.address={address}"], env, tmp_path)
        for job in ("0", "1"):
            assert (tmp_path / "sweep" / job / "results.json").is_file()
        phase["sweep"] = time.time() - t0 - sum(phase.values())
        sweep_nodes = nodes_of_tasks(address, env, "_run_job")  # hydra-ray-launcher's task: one per run
        assert len(sweep_nodes) == 2, sweep_nodes

        crowdbench(["submit", "sweep", "--root", "board"], env, tmp_path)
        crowdbench(["leaderboard", "--root", "board", "--launcher", "ray", "--address", address,
                    *LEADERBOARD_FAST], env, tmp_path)
        phase["submit+leaderboard"] = time.time() - t0 - sum(phase.values())
        results = sorted(p.parent.name for p in (tmp_path / "board" / "results").glob("*/results.json"))
        assert len(results) == 2, results
        board_nodes = nodes_of_tasks(address, env, "_job")  # the leaderboard's task: one per submission
        assert len(board_nodes) == 2, board_nodes
        print(f"sweep tasks on nodes {sorted(sweep_nodes)}; leaderboard tasks on nodes {sorted(board_nodes)}; "
              f"seconds: {', '.join(f'{k} {v:.0f}' for k, v in phase.items())}")
    finally:
        for node in reversed(nodes):
            stop_node(node)
        shutil.rmtree(ray_tmp, ignore_errors=True)
