"""``crowdbench --help``, ``--version`` and ``crowdbench <command> --help`` (Hydra's flags for run and eval)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from crowdbench.algos.registry import names as algo_names
from crowdbench.cli import COMMANDS, main
from crowdbench.models import ENCODERS


def exit_code(args: list[str]) -> int:
    """``main``'s exit code; argparse's ``--help`` ends with ``SystemExit(0)`` instead of returning."""
    try:
        return main(args)
    except SystemExit as e:
        return int(e.code or 0)


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("flag", ["--help", pytest.param("-h", marks=pytest.mark.slow)])  # -h: the same path
def test_every_command_has_help(command, flag, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # Hydra writes nothing for --help; argparse neither: checked below
    assert exit_code([command, flag]) == 0
    out = capsys.readouterr().out
    assert f"crowdbench {command}" in out and len(out.splitlines()) >= 4
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["run", pytest.param("eval", marks=pytest.mark.slow)])
def test_hydra_flags_show_the_config_and_run_nothing(command, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main([command, "--cfg", "job", "algo=sac", "encoder=gcn"]) == 0
    out = capsys.readouterr().out
    assert "name: sac" in out and "name: gcn" in out and "seed: 0" in out
    assert main([command, "--info", "defaults"]) == 0
    assert "Defaults List" in capsys.readouterr().out
    assert main([command, "--help"]) == 0
    assert "Configuration groups" in capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []  # nothing trained, evaluated or written


@pytest.mark.parametrize(("args", "message"), [
    (["--cfg", "job", "encoder=nope"], "crowdbench: error: unknown encoder 'nope'; valid choices: dsrnn,"),
    (["--cfg", "job", "algo.nokey=1"], "crowdbench: error: unknown config key 'algo.nokey'; valid keys under"),
    (["-m", "--cfg", "job", "seed=0,1"], "crowdbench: error: run: Only one of --run, --multirun, --cfg"),
])
def test_hydra_flags_with_bad_input_give_one_line(args, message, capsys):
    assert main(["run", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and len(err.strip().splitlines()) == 1


def test_usage_lists_every_registered_algorithm_and_encoder(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    algos = next(line for line in out.splitlines() if line.strip().startswith("algo="))
    encoders = next(line for line in out.splitlines() if line.strip().startswith("encoder="))
    assert all(a in algos for a in algo_names()) and all(e in encoders for e in ENCODERS)
    assert all(f"crowdbench {c}" in out for c in COMMANDS)
    assert main([]) == 0 and capsys.readouterr().out == out


@pytest.mark.slow
def test_version_through_the_console_script():
    p = subprocess.run([sys.executable, "-m", "crowdbench.entry", "--version"], capture_output=True, text=True,
                       check=False, timeout=120)
    assert p.returncode == 0 and p.stdout.startswith("crowdbench 0.") and "torchrl" in p.stdout, p.stderr
