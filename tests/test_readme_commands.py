"""Every command of the README's command table runs (tiny budgets), so the table cannot drift.

``INVOCATIONS`` maps each documented command to the concrete invocations that exercise it: placeholders
(RUN, OUT, SWEEP_DIR, N, ...) become real paths and values, ``a\\|b`` alternatives each get an invocation,
and tiny budgets are appended. A README row without an entry fails, an entry whose invocation drops a
``key=value`` or ``--flag`` the README shows fails, and every invocation must exit 0.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import require_system

from crowdbench.cli import main
from crowdbench.leaderboard.sandbox import bubblewrap

ROOT = Path(__file__).resolve().parents[1]
PLACEHOLDER = re.compile(r"\.\.\.|\b(RUN|SELFPLAY_RUN|OUT|DIR|SWEEP_DIR|NAME|LABEL|FILE|ADDR|N|S|K)\b")
EVAL = ["eval.episodes=2", "eval.scenes=[hotel]"]
RUN = ["train.pretrain=null", "train.total_frames=256", "train.frames_per_batch=128", "algo.warmup=128", "encoder.dim=8",
       "train.probe_every=1000000", "train.checkpoint_every=1000000", "train.utd=0.0625", *EVAL]
SWEEP = [o for o in RUN if not o.startswith("eval.episodes")] + ["eval.episodes=1"]
SELFPLAY = ["train.pretrain=null", "env.batch=4", "train.frames_per_batch=32", "algo.warmup=64", "algo.batch_size=16", "train.utd=0.125",
            "train.total_frames=64", "train.checkpoint_every=64", "encoder.dim=8", "env.eval_episodes=2",
            "env.eval_scenarios=[circle]"]

# README command -> invocations, in order (later ones use the directories earlier ones wrote: {run} ...)
INVOCATIONS: dict[str, list[list[str]]] = {
    "crowdbench --version": [["--version"]],
    "crowdbench run --help": [["run", "--help"], ["run", "--help", "--cfg", "job"]],  # every command: tests/test_cli_help.py
    "crowdbench eval policy=orca": [["eval", "policy=orca", *EVAL]],
    "crowdbench eval policy=straight": [["eval", "policy=straight", *EVAL]],
    "crowdbench eval policy=oracle": [["eval", "policy=oracle", *EVAL]],
    "crowdbench eval policy=orca orca.safety_margin=0": [["eval", "policy=orca", "orca.safety_margin=0", *EVAL]],
    "crowdbench eval ... eval.scenes=[zara1,zara3,uni_examples]":
        [["eval", "policy=straight", "eval.scenes=[zara1,zara3,uni_examples]", "eval.episodes=2"]],
    "crowdbench eval ... eval.episodes=50": [["eval", "policy=straight", "eval.episodes=50", "eval.scenes=[hotel]"]],
    "crowdbench eval ... eval.save_episodes=true":
        [["eval", "policy=straight", "eval.save_episodes=true", *EVAL, "out={out}"]],
    "crowdbench eval ... out=DIR": [["eval", "policy=straight", *EVAL, "out={tmp}/eval_dir"]],
    # the default recipe with its warm start, on 256 demonstrated steps
    "crowdbench run algo=td3 encoder=gatedgcn": [["run", "algo=td3", "encoder=gatedgcn", *RUN[1:], "train.pretrain_frames=256",
                                                  "train.pretrain_epochs=1", "out={run}"]],
    "crowdbench eval policy=RUN/checkpoint.pt": [["eval", "policy={run}/checkpoint.pt", *EVAL]],
    "crowdbench run algo=ddpg\\|sac\\|ppo encoder=gcn\\|mlp": [
        ["run", "algo=ddpg", "encoder=gcn", *RUN], ["run", "algo=sac", "encoder=mlp", *RUN],
        ["run", "algo=ppo", "encoder=mlp", "algo.minibatch_size=64", "algo.epochs=1",
         *(o for o in RUN if not o.startswith("algo.warmup"))]],
    "crowdbench run experiment=paper": [["run", "experiment=paper", *RUN, "train.utd=0.02"]],
    "crowdbench run ... train.total_frames=N train.max_minutes=30 seed=S":
        [["run", *RUN, "train.total_frames=256", "train.max_minutes=30", "seed=1"]],
    "crowdbench run ... out=RUN resume=true": [["run", *RUN, "train.total_frames=384", "out={run}", "resume=true"]],
    "crowdbench run ... train.progress_reward=0": [["run", *RUN, "train.progress_reward=0"]],
    "crowdbench run ... train.pretrain=orca": [["run", *RUN, "train.pretrain=orca", "train.pretrain_frames=256",
                                                "train.pretrain_epochs=1"]],
    "crowdbench run ... algo.n_steps=5": [["run", *RUN, "algo.n_steps=5"]],
    "crowdbench run ... algo.exploration=ou": [["run", *RUN, "algo.exploration=ou"]],
    "crowdbench run ... algo.critic_lookahead=0": [["run", *RUN, "algo.critic_lookahead=0"]],
    "crowdbench run ... train.human_dropout=0.8": [["run", *RUN, "train.human_dropout=0.8"]],
    "crowdbench run ... train.human_thinning=0.5": [["run", *RUN, "train.human_thinning=0.5"]],
    "crowdbench run train=scratch algo.actor_base=none algo.exploration_sigma=0.3": [
        ["run", *RUN, "train=scratch", "algo.actor_base=none", "algo.exploration_sigma=0.3"]],
    "crowdbench run ... train.playback_speeds=[1.0,2.0]": [["run", *RUN, "train.playback_speeds=[1.0,2.0]"]],
    "crowdbench run ... encoder=rgl encoder.similarity=embedded_gaussian":
        [["run", *RUN, "encoder=rgl", "encoder.similarity=embedded_gaussian", "encoder.compact=false"]],
    "crowdbench run ... encoder=sarl\\|gat\\|dsrnn encoder.score_cap=5":
        [["run", *RUN, f"encoder={e}", "encoder.score_cap=5"] for e in ("sarl", "gat", "dsrnn")],
    "crowdbench run ... algo.replay=prioritized": [["run", *RUN, "algo.replay=prioritized"]],
    "crowdbench run ... algo.replay=prioritized algo.per_weights=true":
        [["run", *RUN, "algo.replay=prioritized", "algo.per_weights=true"]],
    "crowdbench run ... train.logger=tensorboard": [["run", *RUN, "train.logger=tensorboard"]],
    "crowdbench run ... train.logger=wandb": [["run", *RUN, "train.logger=wandb"]],  # offline: Runner's env
    "crowdbench run -m encoder=gatedgcn,gcn,mlp seed=0,1,2":
        [["run", "-m", "encoder=gatedgcn,gcn,mlp", "seed=0,1,2", *SWEEP, "out={tmp}/sweep9"]],
    # seed 0 of each of the 5 rows: the leaderboard commands below then evaluate 6 submissions, not 16
    "crowdbench run -m experiment=leaderboard": [["run", "-m", "experiment=leaderboard", "seed=0", *SWEEP,
                                                  "out={sweep}"]],
    "crowdbench run -m experiment=ppo": [["run", "-m", "experiment=ppo", "seed=0", "env.batch=8", "algo.minibatch_size=64",
                                          "algo.epochs=1", *(o for o in SWEEP if not o.startswith(("algo.", "train.utd"))),
                                          "out={tmp}/ppo_sweep"]],
    "crowdbench run -m experiment=baselines": [["run", "-m", "experiment=baselines", "seed=0", *SWEEP,
                                                "out={tmp}/baselines_sweep"]],
    "crowdbench submit SWEEP_DIR": [["submit", "{sweep}", "--root", "{lb}"]],
    "crowdbench submit RUN --name NAME --entry LABEL":
        [["submit", "{run}", "--name", "tiny_run", "--entry", "tiny TD3", "--root", "{lb}"]],
    "crowdbench leaderboard": [["leaderboard", "--root", "{lb}", "--episodes", "2", "--scenes", "hotel", "--jobs", "2",
                                "--tracks", "v1"]],  # every track: tests/test_tracks.py
    "crowdbench leaderboard --check":
        [["leaderboard", "--check", "--root", "{lb}", "--episodes", "2", "--scenes", "hotel", "--jobs", "2",
          "--tracks", "v1"]],
    # one submission evaluated again in a confined worker (--force: its cached result would be kept); its 5 sweep
    # siblings would run the same code path, at ~8 s of worker start each
    "crowdbench leaderboard --sandbox bubblewrap":
        [["leaderboard", "--root", "{lb}", "--episodes", "2", "--scenes", "hotel", "--tracks", "v1", "--sandbox",
          "bubblewrap", "--only", "tiny_run", "--force"]],
    "crowdbench leaderboard --tracks v1,v2-orca":
        [["leaderboard", "--tracks", "v1,v2-orca", "--root", "{lb}", "--episodes", "2", "--scenes", "hotel",
          "--only", "tiny_run"]],
    "crowdbench leaderboard --site DIR [--site-figures N]":  # figures and the browser: tests/test_site.py
        [["leaderboard", "--root", "{lb}", "--episodes", "2", "--scenes", "hotel", "--tracks", "v1", "--site",
          "{tmp}/site", "--site-figures", "0"]],
    "crowdbench run experiment=selfplay_warmstart":  # 4 agents, 8 demonstrated steps, 64 frames, evaluated on 4
        [["run", "experiment=selfplay_warmstart", "env.n_agents=4", *SELFPLAY, "env.eval_n_agents=[4]",
          "train.pretrain_frames=8", "train.pretrain_epochs=1", "train.pretrain_bc_updates=4", "out={tmp}/sp_ws"]],
    "crowdbench run experiment=selfplay_residual seed=S cpus=1":  # 4 agents, 8 demonstrated steps, 64 frames
        [["run", "experiment=selfplay_residual", "seed=1", "cpus=1", "env.n_agents=4", *SELFPLAY,
          "env.eval_n_agents=[4]", "train.pretrain=orca", "train.pretrain_frames=8", "train.pretrain_epochs=1",
          "train.pretrain_bc_updates=4", "out={tmp}/sp_res"]],
    "crowdbench run experiment=selfplay_ppo_residual method=gatedgcn_mappo\\|gatedgcn_ippo seed=S cpus=1":  # 4 agents, 64 frames
        [["run", "experiment=selfplay_ppo_residual", f"method={m}", "seed=1", "cpus=1", "env.n_agents=4", "env.batch=4",
          "train.frames_per_batch=32", "train.total_frames=64", "train.checkpoint_every=64", "algo.minibatch_size=64",
          "encoder.dim=8", "env.eval_episodes=2", "env.eval_scenarios=[circle]", "env.eval_n_agents=[4]",
          f"out={{tmp}}/sp_ppo_{m}"] for m in ("gatedgcn_mappo", "gatedgcn_ippo")],
    "crowdbench run env=selfplay algo=td3 encoder=gatedgcn":
        [["run", "env=selfplay", "algo=td3", "encoder=gatedgcn", "env.n_agents=4", *SELFPLAY, "out={selfplay}"]],
    "crowdbench run env=selfplay env.n_agents=16 env.scenario=square env.background=students001":
        [["run", "env=selfplay", "env.n_agents=16", "env.scenario=square", "env.background=students001", *SELFPLAY]],
    "crowdbench eval env=selfplay policy=orca\\|straight\\|RUN/checkpoint.pt":
        [["eval", "env=selfplay", f"policy={p}", "env.eval_episodes=2", "env.eval_scenarios=[circle]"]
         for p in ("orca", "straight", "{run}/checkpoint.pt")],
    "crowdbench eval policy=SELFPLAY_RUN/checkpoint.pt": [["eval", "policy={selfplay}/checkpoint.pt", *EVAL]],
    "crowdbench eval env=crowdnav policy=orca\\|straight\\|oracle\\|RUN/checkpoint.pt":
        [["eval", "env=crowdnav", f"policy={p}", "env.eval_episodes=3"]
         for p in ("orca", "straight", "oracle", "{run}/checkpoint.pt")],
    "crowdbench eval env=crowdnav ... env.eval_settings=[circle_n5,circle_n20,square_n5] env.humans=sfm "
    "env.robot_visible=true":
        [["eval", "env=crowdnav", "policy=straight", "env.eval_settings=[circle_n5,circle_n20,square_n5]",
          "env.humans=sfm", "env.robot_visible=true", "env.eval_episodes=2"]],
    "crowdbench run experiment=crowdnav_residual seed=S cpus=1":
        [["run", "experiment=crowdnav_residual", "seed=1", "cpus=1", *RUN, "env.eval_episodes=2"]],
    "crowdbench run env=crowdnav algo=value":
        [["run", "env=crowdnav", "algo=value", "algo.batch=4", "algo.il_episodes=4", "algo.il_steps=3",
          "algo.episodes=4", "algo.train_batches=1", "algo.batch_size=8", "algo.val_every=0", "env.time_limit=20",
          "env.eval_episodes=3"]],
    "crowdbench run experiment=value_replay":
        [["run", "experiment=value_replay", "algo.batch=4", "algo.il_episodes=4", "algo.il_steps=3", "algo.episodes=4",
          "algo.train_batches=1", "algo.batch_size=8", "algo.val_every=0", "algo.keep_best=false", "encoder.dim=8",
          *EVAL]],
    "crowdbench run env=crowdnav algo=td3 encoder=gatedgcn":
        [["run", "env=crowdnav", "algo=td3", "encoder=gatedgcn", *RUN, "env.eval_episodes=2"]],
    "crowdbench eval env.humans=reactive_replay policy=orca\\|straight\\|RUN/checkpoint.pt":
        [["eval", "env.humans=reactive_replay", f"policy={p}", *EVAL] for p in ("orca", "straight", "{run}/checkpoint.pt")],
    "crowdbench run env.humans=reactive_replay algo=td3 encoder=gatedgcn":
        [["run", "env.humans=reactive_replay", "algo=td3", "encoder=gatedgcn", *RUN]],
    "crowdbench eval ... viz.record=true [viz.episodes=[0,21]] [viz.scenes=[students003]]":
        [["eval", "policy=straight", "viz.record=true", "viz.episodes=[0,249]", "viz.scenes=[hotel]", *EVAL,
          "out={tmp}/viz_eval"]],
    "crowdbench viz OUT [--episode N] [--scene S] [--out FILE.png]":
        [["viz", "{out}", "--episode", "0", "--scene", "hotel", "--out", "{tmp}/ep.png"]],
    "crowdbench viz OUT --grid K [--scene S]": [["viz", "{out}", "--grid", "2", "--scene", "hotel",
                                                 "--out", "{tmp}/grid.png"]],
    "crowdbench viz OUT [--episode N] --video FILE.gif\\|FILE.mp4 [--fps F]":  # mp4: tests/test_viz.py
        [["viz", "{out}", "--episode", "0", "--video", "{tmp}/ep.gif"]],
    "crowdbench plot RUN [RUN ...] [--out FILE.png] [--smooth N]":
        [["plot", "{run}", "{run}", "--out", "{tmp}/curves.png", "--smooth", "2"]],
}


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    table = text.split("| command |", 1)[1].split("\n\n", 1)[0]
    return [m.group(1) for m in re.finditer(r"^\| `([^`]+)` \|", table, re.MULTILINE)]


def shown_tokens(command: str) -> list[str]:
    """The README command's concrete ``key=value`` and ``--flag`` tokens (alternatives split)."""
    out, depth = [], 0
    for tok in command.split()[2:]:
        if depth or tok.startswith("["):  # an optional [...] group (it may hold a Hydra list): not required
            depth += tok.count("[") - tok.count("]")
            continue
        if not PLACEHOLDER.search(tok):
            out.append(tok)
    return out


def test_every_readme_command_has_invocations():
    commands = readme_commands()
    assert len(commands) >= 30
    assert [c for c in commands if c not in INVOCATIONS] == []
    assert [c for c in INVOCATIONS if c not in commands] == []  # no stale entry


@pytest.mark.parametrize("command", list(INVOCATIONS))
def test_invocations_keep_what_the_readme_shows(command):
    invocations = INVOCATIONS[command]
    sub = command.split()[1]
    flat = [" ".join(i) for i in invocations]
    assert all(i[0] == sub for i in invocations)
    for tok in shown_tokens(command):
        if "\\|" in tok:  # policy=orca\|straight\|... : each alternative in some invocation
            key, _, vals = tok.partition("=")
            for v in vals.split("\\|"):
                if not PLACEHOLDER.search(v):
                    assert any(f"{key}={v}" in f for f in flat), (command, v)
        else:
            assert all(tok in i for i in invocations), (command, tok)


# placeholder -> the README command whose invocation writes it; {lb} is written by both submit commands
PRODUCERS = {"run": "crowdbench run algo=td3 encoder=gatedgcn", "out": "crowdbench eval ... eval.save_episodes=true",
             "sweep": "crowdbench run -m experiment=leaderboard",
             "selfplay": "crowdbench run env=selfplay algo=td3 encoder=gatedgcn"}
SUBMITS = ("crowdbench submit SWEEP_DIR", "crowdbench submit RUN --name NAME --entry LABEL")
CHECKS = {"crowdbench leaderboard --check": "crowdbench leaderboard"}


def prerequisites(command: str) -> list[str]:
    """The README commands that must have run before ``command`` (they write the directories it reads)."""
    text = " ".join(" ".join(i) for i in INVOCATIONS[command])
    deps = [c for key, c in PRODUCERS.items() if "{" + key + "}" in text and c != command]
    if "{lb}" in text and command not in SUBMITS:
        deps += SUBMITS
    if command in CHECKS:  # it compares with the tables another command wrote
        deps.append(CHECKS[command])
    return deps


class Runner:
    """Runs README commands once per test module (per xdist worker), each after its prerequisites."""

    def __init__(self, tmp: Path):
        self.places = {"tmp": tmp, "run": tmp / "run", "out": tmp / "eval_out", "sweep": tmp / "sweep",
                       "lb": tmp / "lb", "selfplay": tmp / "selfplay"}
        (tmp / "lb" / "submissions").mkdir(parents=True)
        self.done: dict[str, list[str]] = {}
        self.output: dict[str, str] = {}  # what an in-process command printed
        # train.logger=wandb: nothing sent, W&B's settings and cache under tmp
        self.wandb = {"WANDB_MODE": "offline", "WANDB_SILENT": "true", "WANDB_DIR": str(tmp),
                      "WANDB_CACHE_DIR": str(tmp / "wandb-cache"), "WANDB_CONFIG_DIR": str(tmp / "wandb-config")}
        self.env = {**os.environ, "OMP_NUM_THREADS": "1", "RL_WARNINGS": "False", **self.wandb}

    def ensure(self, command: str, capsys) -> list[str]:
        """The failures of ``command``'s invocations (empty: all exited 0); a failed prerequisite fails it."""
        if command in self.done:
            return self.done[command]
        failed = [f"prerequisite {dep!r}: {err}" for dep in prerequisites(command)
                  for err in self.ensure(dep, capsys)]
        for inv in INVOCATIONS[command] if not failed else []:
            args = [a.format(**self.places) for a in inv]
            if args[:2] == ["run", "-m"]:  # Hydra's multirun owns global state: a fresh interpreter
                p = subprocess.run([sys.executable, "-m", "crowdbench", *args], env=self.env, capture_output=True,
                                   text=True, timeout=900, check=False, cwd=self.places["tmp"])
                rc, err = p.returncode, p.stderr[-500:]
            else:
                saved = {k: os.environ.get(k) for k in self.wandb}
                os.environ.update(self.wandb)
                try:
                    rc = main(args)
                finally:
                    for k, v in saved.items():
                        if v is None:
                            os.environ.pop(k)
                        else:
                            os.environ[k] = v
                captured = capsys.readouterr()
                self.output[command] = captured.out + captured.err
                err = captured.err[-3000:]
            if rc != 0:
                failed.append(f"crowdbench {' '.join(args)}: exit {rc}: {err}")
        self.done[command] = failed
        return failed


@pytest.fixture(scope="module")
def runner(tmp_path_factory):
    return Runner(tmp_path_factory.mktemp("readme"))


def written(places: dict) -> dict:
    """What some commands must leave behind, beyond exit code 0."""
    subs = places["lb"] / "submissions"
    return {
        "crowdbench leaderboard": lambda: (places["lb"] / "README.md").is_file()
        and {"tiny_run", "sarl_td3_residual_sigma045_s0"} <= {p.name for p in subs.iterdir()}
        and len(list(subs.iterdir())) == 6,  # the 5 leaderboard rows' seed 0 + 1
        "crowdbench eval ... viz.record=true [viz.episodes=[0,21]] [viz.scenes=[students003]]":
            lambda: (places["tmp"] / "viz_eval" / "recordings").is_dir(),
        "crowdbench leaderboard --site DIR [--site-figures N]": lambda: (places["tmp"] / "site" / "index.html").is_file(),
    }


def quick(command: str) -> bool:
    """In the quick suite: every command but training runs, sweeps and the leaderboard, plus the runs
    the quick commands read (``pytest --full`` runs them all)."""
    sub = INVOCATIONS[command][0][0]
    return sub not in ("run", "submit", "leaderboard") or command in (PRODUCERS["run"], PRODUCERS["selfplay"])


def _param(command: str):
    # commands sharing the sweep and the leaderboard root stay on one xdist worker (--dist loadgroup), so
    # the 15-run sweep they need is trained once
    text = " ".join(" ".join(i) for i in INVOCATIONS[command])
    marks = [pytest.mark.xdist_group("readme_leaderboard")] if "{lb}" in text or "{sweep}" in text else []
    return pytest.param(command, marks=marks + [pytest.mark.slow] * (not quick(command)))


@pytest.mark.parametrize("command", [_param(c) for c in INVOCATIONS])
def test_readme_command_runs(command, runner, monkeypatch, capsys):
    if "--sandbox bubblewrap" in command:
        require_system("bwrap", bubblewrap() is not None)
    monkeypatch.chdir(runner.places["tmp"])  # default outputs/ go to the scratch directory
    if "--sandbox bubblewrap" in command:  # tiny_run's cached v1 result is evaluated again, confined
        for dep in prerequisites(command):
            assert runner.ensure(dep, capsys) == [], dep
        result = runner.places["lb"] / "results" / "tiny_run" / "results.json"
        before = result.stat().st_mtime_ns if result.is_file() else None
    assert runner.ensure(command, capsys) == []
    if "--sandbox bubblewrap" in command:
        assert "CONFINED by bubblewrap" in runner.output[command] and result.is_file()
        assert result.stat().st_mtime_ns != before
    check = written(runner.places).get(command)
    assert check is None or check(), command
