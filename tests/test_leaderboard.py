"""Leaderboard harness: valid and malformed submissions, external encoders, cache, --check."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
import yaml
from torch import nn

from crowdbench.algos.actors import build_actor
from crowdbench.algos.checkpoint import FORMAT, save_checkpoint
from crowdbench.cli import main as cli_main
from crowdbench.leaderboard import diff_rows, run
from crowdbench.models import ENCODERS

REPO = Path(__file__).resolve().parents[1]
FAST = {"episodes": 2, "scenes": ["hotel"], "tracks": ["v1"]}  # tests evaluate a subset (unofficial)


def write_yaml(root: Path, name: str, text: str) -> Path:
    d = root / "submissions" / name
    d.mkdir(parents=True, exist_ok=True)
    (d / "submission.yaml").write_text(text)
    return d


def toy_checkpoint(path: Path, encoder: dict, algo: str = "td3", actor_encoder: dict | None = None,
                   env: dict | None = None) -> None:
    """A tiny untrained actor saved in the training checkpoint format (state dicts + config)."""
    torch.manual_seed(0)
    actor = build_actor(algo, dict(actor_encoder or encoder), 1.0, squash="radial")
    cfg = {"algo": {"name": algo, "actor_squash": "radial"}, "encoder": dict(encoder),
           "env": env or {"v_max": 1.0, "frame": "rotate"}}
    save_checkpoint(path, {"config": cfg, "actor": actor.state_dict(), "frames": 0})


MLP = {"name": "mlp", "dim": 8, "hidden": [16], "max_humans": 40}


def learned_yaml(name, encoder="mlp", extra=""):
    return (f"name: {name}\nkind: learned\nentry: Toy MLP\nencoder: {encoder}\nalgo: td3\nseed: 0\n"
            f"authors: [tester]\n{extra}")


def add_straight(root):
    write_yaml(root, "straight", "name: straight\nkind: baseline\nentry: Straight to goal\npolicy: straight\n"
                                 "authors: [crowdbench]\n")


def add_toy(root, name="toy"):
    d = write_yaml(root, name, learned_yaml(name))
    toy_checkpoint(d / "checkpoint.pt", MLP)


class Pickled(nn.Module):  # a checkpoint holding this object needs code execution to load
    pass


@pytest.mark.slow
def test_valid_and_malformed_submissions(tmp_path):
    root = tmp_path / "lb"
    add_straight(root)
    add_toy(root)
    write_yaml(root, "bad_yaml", "name: bad_yaml\nkind: [learned\n")
    # (its own row: a label is shared only by one encoder, algo and recipe, crowdbench/leaderboard/entries.py)
    write_yaml(root, "bad_encoder", learned_yaml("bad_encoder", encoder="nosuchencoder").replace("Toy MLP", "Bad"))
    toy_checkpoint(root / "submissions" / "bad_encoder" / "checkpoint.pt", MLP)
    d = write_yaml(root, "bad_shapes", learned_yaml("bad_shapes"))
    toy_checkpoint(d / "checkpoint.pt", MLP, actor_encoder={**MLP, "dim": 12})  # weights don't fit the config
    d = write_yaml(root, "bad_pickle", learned_yaml("bad_pickle"))
    cfg = {"algo": {"name": "td3"}, "encoder": MLP, "env": {"v_max": 1.0, "frame": "rotate"}}
    torch.save({"format": FORMAT, "config": cfg, "actor": Pickled(), "frames": 0}, d / "checkpoint.pt")
    write_yaml(root, "bad_field", "name: bad_field\nkind: baseline\npolicy: straight\n")  # no authors
    write_yaml(root, "bad_type", "name: bad_type\nkind: baseline\npolicy: orca\nauthors: [a]\nseed: zero\n")
    write_yaml(root, "bad_param", "name: bad_param\nkind: baseline\npolicy: orca\nauthors: [a]\n"
                                  "overrides: {safety_marginn: 0.3}\n")
    log = []
    rc = run(root, log=log.append, **FAST)
    assert rc == 1  # some submissions failed ...
    text = "\n".join(log)
    errors = [line for line in log if line.startswith("crowdbench leaderboard: error:")]
    assert len(errors) == 7 and all("\n" not in e for e in errors)  # one line each

    def err(name):
        (line,) = [e for e in errors if f"submissions/{name}/submission.yaml" in e]
        return line

    assert "malformed YAML at line 3" in err("bad_yaml") and "expected ',' or ']'" in err("bad_yaml")
    assert "field 'encoder'" in err("bad_encoder") and "unknown encoder 'nosuchencoder'" in err("bad_encoder")
    assert "field 'checkpoint'" in err("bad_shapes") and "does not fit its model" in err("bad_shapes")
    assert "field 'checkpoint'" in err("bad_pickle") and "unsafe" in err("bad_pickle")
    assert "field 'authors': missing" in err("bad_field")
    assert "field 'seed': must be an integer" in err("bad_type")
    assert "field 'overrides.safety_marginn': unknown orca parameter" in err("bad_param")
    # ... while the others still ran and appear in the generated table
    assert "toy: evaluated" in text and "straight: evaluated" in text
    readme = (root / "README.md").read_text()
    assert readme.startswith("<!-- GENERATED") and "DO NOT EDIT" in readme
    success = readme.split("## Success rate")[1].split("##")[0]
    assert re.search(r"\| Toy MLP \| 1 \| \d\.\d{3} \[", success)
    assert "| Straight to goal | 1 |" in success
    assert "## Rejected submissions" in readme and "submissions/bad_pickle/submission.yaml" in readme
    assert str(tmp_path) not in readme  # paths are relative to the leaderboard root
    res = (root / "results" / "toy" / "results.json").read_text()
    assert '"episode_outcomes"' in res and not (root / "results" / "bad_shapes").exists()
    assert (root / "leaderboard.png").stat().st_size > 1000


@pytest.mark.slow
def test_check_cache_and_only(tmp_path):
    root = tmp_path / "lb"
    add_straight(root)
    add_toy(root)
    assert run(root, log=lambda m: None, **FAST) == 0
    committed = (root / "README.md").read_text()
    log = []
    assert run(root, check=True, log=log.append, **FAST) == 0  # deterministic: a fresh evaluation matches
    assert "matches" in log[-1]
    # cache: unchanged submissions are not re-evaluated; --only limits the work
    log.clear()
    assert run(root, log=log.append, **FAST) == 0
    assert any("toy: unchanged, cached" in m for m in log) and not any("evaluated in" in m for m in log)
    log.clear()
    assert run(root, only=["straight"], force=True, log=log.append, **FAST) == 0
    assert any(m.startswith("straight: evaluated") for m in log) and not any(m.startswith("toy: ") for m in log)
    assert (root / "README.md").read_text() == committed
    # a hand-edited table is detected, naming the row
    edited = re.sub(r"(\| Straight to goal \| 1 \| )\d\.\d{3}", r"\g<1>0.999", committed, count=1)
    assert edited != committed
    (root / "README.md").write_text(edited)
    log.clear()
    assert run(root, check=True, log=log.append, **FAST) == 1
    assert "FAILED" in log[-1] and "[Success rate (Tables III / IV)] row 'Straight to goal'" in log[-1]
    assert (root / "README.md").read_text() == edited  # --check writes nothing
    # a changed submission is re-evaluated without --force
    yaml = root / "submissions" / "toy" / "submission.yaml"
    yaml.write_text(yaml.read_text() + "notes: changed\n")
    log.clear()
    run(root, log=log.append, **FAST)
    assert any(m.startswith("toy: evaluated") for m in log)


@pytest.mark.slow
def test_seeds_grouped(tmp_path):
    root = tmp_path / "lb"
    for s in (0, 1):
        d = write_yaml(root, f"toy_s{s}", learned_yaml(f"toy_s{s}").replace("seed: 0", f"seed: {s}"))
        toy_checkpoint(d / "checkpoint.pt", MLP)
    assert run(root, log=lambda m: None, **FAST) == 0
    readme = (root / "README.md").read_text()
    # the mean over seeds [95% two-level bootstrap interval]
    assert re.search(r"\| Toy MLP \| 2 \| \d\.\d{3} \[\d\.\d{3}, \d\.\d{3}\] \|", readme)
    assert "## Per-seed results" in readme and "| Toy MLP | toy_s1 | 1 |" in readme


@pytest.mark.slow
def test_external_encoder_import_and_entry_point(tmp_path, monkeypatch):
    """Both ways of naming an external encoder; its code is imported by the submission's worker
    process only, never by the harness."""
    import sys

    from crowdbench.leaderboard import worker

    monkeypatch.syspath_prepend(str(REPO))
    from examples.tiny_encoder import TinyEncoder

    tiny_src = (REPO / "examples" / "tiny_encoder.py").read_text()
    root = tmp_path / "lb"
    enc = {"name": "tiny_example", "dim": 8}
    monkeypatch.setitem(ENCODERS, "tiny_example", TinyEncoder)  # to build the toy checkpoint; removed after
    d = write_yaml(root, "tiny", learned_yaml("tiny", "tiny_example", "encoder_import: tiny_encoder:TinyEncoder\n"))
    (d / "tiny_encoder.py").write_text(tiny_src)  # a file next to the yaml
    toy_checkpoint(d / "checkpoint.pt", enc)
    # an installed package advertising the encoder: a distribution on the worker's path
    site = tmp_path / "site"
    (site / "tinyep-0.1.dist-info").mkdir(parents=True)
    (site / "tinyep-0.1.dist-info" / "METADATA").write_text("Metadata-Version: 2.1\nName: tinyep\nVersion: 0.1\n")
    (site / "tinyep-0.1.dist-info" / "entry_points.txt").write_text(
        "[crowdbench.encoders]\ntiny_ep = tinyep_encoder:TinyEncoder\n")
    (site / "tinyep_encoder.py").write_text(tiny_src)
    environment = worker.environment
    monkeypatch.setattr(worker, "environment", lambda scratch: {
        **environment(scratch), "PYTHONPATH": f"{environment(scratch)['PYTHONPATH']}:{site}"})
    monkeypatch.setitem(ENCODERS, "tiny_ep", TinyEncoder)
    d = write_yaml(root, "tiny_ep", learned_yaml("tiny_ep", "tiny_ep", "encoder_entry_points: crowdbench.encoders\n")
                   .replace("Toy MLP", "Tiny (entry point)"))
    toy_checkpoint(d / "checkpoint.pt", {"name": "tiny_ep", "dim": 8})
    del ENCODERS["tiny_example"], ENCODERS["tiny_ep"]  # the worker must register them itself
    d = write_yaml(root, "tiny_bad", learned_yaml("tiny_bad", "tiny_bad", "encoder_import: examples.nothere:X\n"))
    toy_checkpoint(d / "checkpoint.pt", MLP)
    log = []
    assert run(root, log=log.append, **FAST) == 1
    assert "tiny_example" not in ENCODERS and "tiny_ep" not in ENCODERS  # nothing ran in the harness
    assert not any(getattr(m, "__file__", None) and "tiny_encoder" in str(m.__file__) and "examples" not in
                   str(m.__file__) for m in list(sys.modules.values()))
    assert any(m.startswith("tiny: evaluated") for m in log) and any(m.startswith("tiny_ep: evaluated") for m in log)
    (bad,) = [m for m in log if "tiny_bad" in m and "error" in m]
    assert "field 'encoder_import': 'examples.nothere' is not a module file inside the submission directory" in bad


def test_cli_dispatch_and_bad_options(tmp_path, capsys):
    root = tmp_path / "lb"
    add_straight(root)
    assert cli_main(["leaderboard", "--root", str(root), "--episodes", "1", "--scenes", "eth", "--tracks", "v1"]) == 0
    assert "Straight to goal" in (root / "README.md").read_text()
    assert cli_main(["leaderboard", "--root", str(root), "--only", "nosuch"]) == 1
    assert "unknown submission(s) nosuch" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        cli_main(["leaderboard", "--root", str(root), "--scenes", "students001"])
    assert e.value.code == 2  # the training scene is not an evaluation scene


def test_diff_rows_names_sections():
    a = "## A\n\n| m | x |\n|---|---|\n| one | 1 |\n| two | 2 |\n"
    b = a.replace("| two | 2 |", "| two | 3 |")
    (msg,) = diff_rows(a, b)
    assert msg.startswith("[A] row 'two': differs")


@pytest.mark.slow
def test_parallel_jobs_give_the_same_table(tmp_path):
    root = tmp_path / "lb"
    add_straight(root)
    add_toy(root)
    assert run(root, log=lambda m: None, **FAST) == 0
    log = []
    assert run(root, check=True, jobs=2, log=log.append, **FAST) == 0, log  # 2 worker processes, same numbers


@pytest.mark.slow
def test_submit_a_run(tmp_path, capsys):
    """`crowdbench submit` turns a run into a submission the harness evaluates; it records the overrides."""
    from omegaconf import OmegaConf

    from crowdbench.cli import compose

    cfg = OmegaConf.to_container(compose(["encoder=mlp", "encoder.dim=8", "encoder.hidden=[16]", "algo.n_steps=3",
                                          "seed=4"]), resolve=True)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    actor = build_actor("td3", dict(cfg["encoder"]), 1.0, squash=cfg["algo"]["actor_squash"])
    save_checkpoint(run_dir / "checkpoint.pt", {"config": cfg, "actor": actor.state_dict(), "frames": 640,
                                                "loss": {"w": torch.zeros(1000, 100)}})
    root = tmp_path / "lb"
    assert cli_main(["submit", str(run_dir), "--name", "mine_s4", "--entry", "Mine", "--root", str(root)]) == 0
    sub = yaml.safe_load((root / "submissions" / "mine_s4" / "submission.yaml").read_text())
    assert sub["seed"] == 4 and sub["encoder"] == "mlp" and sub["kind"] == "learned"
    assert {"encoder.dim=8", "encoder.hidden=[16]", "algo.n_steps=3", "seed=4"} <= set(sub["overrides"])
    assert not any(o.startswith("algo.gamma") for o in sub["overrides"])  # defaults are not repeated
    slim = torch.load(root / "submissions" / "mine_s4" / "checkpoint.pt", weights_only=True)
    assert "loss" not in slim and slim["frames"] == 640  # critics and optimisers dropped
    assert run(root, **FAST) == 0
    assert "| Mine | 1 |" in (root / "README.md").read_text()
    assert cli_main(["submit", str(run_dir), "--name", "mine_s4", "--entry", "Mine", "--root", str(root)]) == 2
    assert "already exists" in capsys.readouterr().err


@pytest.mark.slow
def test_fingerprint_covers_every_module_an_evaluation_loads(tmp_path):
    """Evaluate one submission of each kind in a fresh interpreter; every crowdbench module it
    loaded must be hashed into the cache fingerprint (else a change to it would leave stale numbers
    cached). The harness itself is versioned by HARNESS_VERSION instead."""
    import json
    import subprocess
    import sys

    from crowdbench.leaderboard import PACKAGE_DIR, code_files

    root = tmp_path / "lb"
    add_straight(root)
    add_toy(root)
    write_yaml(root, "orca", "name: orca\nkind: baseline\nentry: ORCA\npolicy: orca\nauthors: [a]\n")
    write_yaml(root, "oracle", "name: oracle\nkind: oracle\nentry: Oracle\nprivileged: true\nauthors: [a]\n")
    # the learned entry's policy is built and run in its worker process: load it here as the worker does
    script = ("import json, sys; from pathlib import Path; from crowdbench.leaderboard import run; "
              "from crowdbench.leaderboard.loading import dummy_obs, learned_policy; "
              "from crowdbench.leaderboard.submission import read_submission; "
              f"assert run({str(root)!r}, episodes=1, scenes=['hotel'], log=lambda m: None) == 0; "
              f"learned_policy(read_submission(Path({str(root)!r}) / 'submissions' / 'toy')).act(dummy_obs()); "
              "print(json.dumps(sorted(m.__file__ for n, m in sys.modules.items() "
              "if n.startswith('crowdbench') and getattr(m, '__file__', None))))")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    loaded = {Path(f).resolve() for f in json.loads(out.stdout.splitlines()[-1])}
    assert {PACKAGE_DIR / "algos" / "actors.py", PACKAGE_DIR / "baselines" / "oracle.py"} <= loaded
    hashed = set(code_files())
    # everything loaded is hashed, except the harness package itself (versioned by HARNESS_VERSION) and the
    # published lists' hashes (protocols/lists.py: a check that can refuse an evaluation, never change a number)
    # and the plots' colours (viz/palette.py: drawn after the evaluation, never a number)
    # (the harness's submission checks name the algorithms from their registry without importing their training
    # code, and the frames it accepts are the env's own, envs/rules.py, which is hashed: no algos, models or
    # config schema module is loaded outside the fingerprint)
    assert {p.relative_to(PACKAGE_DIR).parts[0] for p in loaded - hashed} == {"leaderboard", "protocols", "viz"}
    assert {PACKAGE_DIR / "algos" / "checkpoint.py", PACKAGE_DIR / "algos" / "actors.py"} <= hashed
    assert {p.relative_to(PACKAGE_DIR).as_posix() for p in loaded - hashed if p.parent.name == "viz"} == \
        {"viz/__init__.py", "viz/palette.py"}
    assert [p for p in loaded - hashed if p.parent.name == "protocols"] == [PACKAGE_DIR / "protocols" / "lists.py"]
    assert PACKAGE_DIR / "policies.py" in hashed  # the registry builds every baseline
    assert PACKAGE_DIR / "algos" / "train.py" not in hashed  # training code does not invalidate results


def test_registry_builds_the_same_policy_for_cli_and_leaderboard(tmp_path):
    """`crowdbench eval policy=orca` and an ORCA submission get the same constructor arguments,
    including the env config's radii and dt; bad names and keys are one-line errors naming the choices."""
    from crowdbench import policies
    from crowdbench.cli import UsageError, compose, make_policy
    from crowdbench.leaderboard import build_policy, read_submission

    root = tmp_path / "lb"
    d = write_yaml(root, "orca", "name: orca\nkind: baseline\npolicy: orca\nseed: 3\nauthors: [a]\n"
                                 "overrides: {safety_margin: 0.25}\n")
    lb = build_policy(read_submission(d))
    cli = make_policy("orca", compose(["seed=3", "orca.safety_margin=0.25"]))
    assert {k: v for k, v in vars(lb).items() if k != "name"} == {k: v for k, v in vars(cli).items() if k != "name"}
    assert make_policy("orca", compose(["env.robot_radius=0.3"])).robot_radius == 0.3  # env values reach ORCA
    assert make_policy("straight", compose(["env.v_max=0.5"])).v_max == 0.5
    with pytest.raises(UsageError, match=r"unknown policy 'nosuch'; valid: orca, straight, oracle or a checkpoint"):
        make_policy("nosuch", compose([]))
    with pytest.raises(policies.PolicyError, match=r"unknown oracle parameter 'seed'; valid: beam, cell") as e:
        policies.build("oracle", None, {"seed": 1})
    assert e.value.key == "seed"
    with pytest.raises(policies.PolicyError, match=r"^oracle: oracle.headings: must be >= 1 \(got 0\)"):
        policies.build("oracle", None, {"oracle.headings": 0})


def test_experiment_field(tmp_path):
    from crowdbench.leaderboard import SubmissionError, read_submission

    root = tmp_path / "lb"
    d = write_yaml(root, "toy", learned_yaml("toy", extra="experiment: leaderboard_long\n"))
    toy_checkpoint(d / "checkpoint.pt", MLP)
    assert read_submission(d).data["experiment"] == "leaderboard_long"
    too_long = "must be a non-empty string of at most 200 characters, got"
    for value, problem in (("[a, b]", "must be a string"), ("x" * 201, f"{too_long} 201"), ("''", f"{too_long} 0")):
        (d / "submission.yaml").write_text(learned_yaml("toy", extra=f"experiment: {value}\n"))
        with pytest.raises(SubmissionError, match=f"field 'experiment': {problem}"):
            read_submission(d)
    d = write_yaml(root, "orca", "name: orca\nkind: baseline\npolicy: orca\nauthors: [a]\nexperiment: x\n")
    with pytest.raises(SubmissionError, match="field 'experiment': only learned submissions"):
        read_submission(d)


def committed_results() -> list[dict]:
    """Protocol v1's committed results of the entries its tables show (baselines, the oracle, v1-trained)."""
    import json

    from crowdbench.leaderboard.track_tables import trained_on

    results = [json.loads(p.read_text()) for p in sorted((REPO / "leaderboard" / "results").glob("*/results.json"))]
    return [r for r in results if trained_on(r) in (None, "v1")]


def test_readme_block_is_rendered_from_the_committed_results():
    """The results block of the top-level README.md is what the harness renders from
    leaderboard/results/*/results.json (pure rendering, no evaluation); a changed number is caught."""
    from crowdbench.envs.protocol import EVAL_SCENES
    from crowdbench.leaderboard import render

    results = committed_results()
    committed = render.read_block((REPO / "README.md").read_text())
    assert render.render_block(results, list(EVAL_SCENES), None) == committed
    assert "| 6 | ORCA | 1 | 0.935 | 0.892 | 0.884 |" in committed  # ranked by the paper-scene average, first
    assert "ORCA 0.935 [0.918, 0.949] (1.656 [1.399, 1.913] dangers per episode)" in committed
    (orca,) = [r for r in results if r["meta"]["submission"] == "orca"]
    orca["scenes"]["hotel"]["success_rate"]["mean"] = 0.5
    rows = render.diff_rows(committed, render.render_block(results, list(EVAL_SCENES), None))
    (row,) = [m for m in rows if m.startswith("[] row 'ORCA': differs")]  # rows named by method, not rank
    fresh = row.split("fresh:")[1]
    rank = int(re.search(r"\| (\d+) \| ORCA \| 1 \| 0\.816 \|", fresh).group(1))
    assert rank > 6 and "0.500" in fresh  # a lower average, a lower rank
    ranks = [m for m in rows if m.startswith("[] row '") and "Average" not in m and not m.startswith("[] row 'ORCA':")]
    # the entries ORCA fell behind (shown between 0.816 and 0.935) moved up one rank; one shown at 0.935 shared
    # ORCA's rank and keeps it
    passed = [g for g in render.group_results(results) if g[0]["meta"]["entry"] != "ORCA"
              and 0.816 < round(render.success_score(g, list(EVAL_SCENES)) or 0.0, 3) < 0.935]
    assert len(ranks) == len(passed) > 3
    (sentence,) = [m for m in rows if m.startswith("[] row 'Average success")]
    assert "ORCA 0.816" in sentence  # the average moved too


def test_docs_blocks_are_rendered_from_the_committed_results():
    """docs/results.md's block (summary of every entry, per-metric tables of the baselines) and
    docs/reproduction.md's paper-scene tables are what the harness renders from the committed
    results (pure rendering, no evaluation); a changed number is caught in each."""
    from crowdbench.envs.protocol import EVAL_SCENES
    from crowdbench.leaderboard import render

    results = committed_results()
    docs = (REPO / "docs" / "results.md").read_text()
    reproduction = (REPO / "docs" / "reproduction.md").read_text()
    assert render.blocks_in(docs) == ["docs-results"]
    assert render.blocks_in(reproduction) == ["reproduction-success", "reproduction-nav-time", "reproduction-dangers"]
    training = (REPO / "docs" / "training.md").read_text()
    assert render.blocks_in(training) == ["experiment-leaderboard"]
    for text in (docs, reproduction, training):
        assert render.regenerate(text, results, list(EVAL_SCENES), None) == text
    # the card's recipe with each encoder: experiment=leaderboard's rows and ORCA, not the rows from scratch
    block = render.read_block(training, "experiment-leaderboard")
    assert "| ORCA | 1 | 0.935 [0.918, 0.949] | 0.892 | 0.884 | 0.976 | 0.988 | 1.656 [1.399, 1.913] |" in block
    assert "| MP-GatedGCN-RL (TD3, gatedgcn, residual on ORCA, exploration sigma 0.45) | 3 | 0.958 [0.948, 0.968] |" in block
    assert "| 1 | RGL (TD3, rgl, residual on ORCA, exploration sigma 0.45) | 3 | 0.971 [0.959, 0.981] |" in block
    assert "GCN-RL (TD3, gcn) |" not in block and "Oracle" not in block
    committed = render.read_block(docs, "docs-results")
    assert "| 6 | ORCA | 1 | 0.935 [0.918, 0.949] | 1.656 [1.399, 1.913] |" in committed
    assert "| orca | 0.892 [0.847, 0.925] | 0.884 [0.838, 0.918] |" in committed  # Wilson, from results.json
    (orca,) = [r for r in results if r["meta"]["submission"] == "orca"]
    orca["scenes"]["students003"]["jerk"]["mean"] = 9.0
    (row,) = render.diff_rows(committed, render.render_docs_block(results, list(EVAL_SCENES), None))
    assert row.startswith("[Jerk (m/s^3)] row 'orca': differs") and "9.00 [" in row
    orca["scenes"]["hotel"]["success_rate"]["mean"] = 0.5
    rows = [r.split(":")[0] for r in render.diff_rows(committed, render.render_docs_block(results, list(EVAL_SCENES),
                                                                                           None))]
    assert {"[] row 'ORCA'", "[Success rate] row 'orca'", "[Jerk (m/s^3)] row 'orca'"} <= set(rows)
    assert all(r.startswith("[] row '") for r in rows if "orca" not in r)  # the others: their rank only
    old = render.read_block(reproduction, "reproduction-success")
    rows = render.diff_rows(old, render.BLOCKS["reproduction-success"](results, list(EVAL_SCENES), None))
    (row,) = [m for m in rows if m.startswith("[] row 'ORCA': differs")]
    assert "0.500" in row


def test_an_edit_made_while_the_leaderboard_runs_is_kept(tmp_path, monkeypatch):
    """The README's prose edited after the run started (here: right after its blocks were located) survives
    the run's rewrite of the results block: the block is replaced in the file as it is when written."""
    from crowdbench.leaderboard import board

    root = tmp_path / "lb"
    add_straight(root)
    readme = tmp_path / "README.md"
    readme.write_text("# Title\n\n<!-- generated:results:start -->\nold\n<!-- generated:results:end -->\n\nmore\n")
    located = board._targets

    def located_then_edited(*args, **kwargs):
        out = located(*args, **kwargs)
        readme.write_text(readme.read_text().replace("more", "an edit made during the run"))
        return out

    monkeypatch.setattr(board, "_targets", located_then_edited)
    assert run(root, readme=readme, log=lambda m: None, **FAST) == 0
    text = readme.read_text()
    assert text.endswith("\n\nan edit made during the run\n") and "old" not in text and "| Straight to goal | 1 |" in text


@pytest.mark.slow
def test_readme_block_written_checked_and_never_touched_by_a_scratch_root(tmp_path, monkeypatch, capsys):
    root = tmp_path / "lb"
    add_straight(root)
    readme = tmp_path / "README.md"
    text = "# Title\n\nprose\n\n<!-- generated:results:start -->\nold\n<!-- generated:results:end -->\n\nmore\n"
    readme.write_text(text)
    assert run(root, readme=readme, log=lambda m: None, **FAST) == 0
    new = readme.read_text()
    assert new.startswith("# Title\n\nprose\n\n") and new.endswith("\n\nmore\n") and "old" not in new
    assert "UNOFFICIAL subset" in new and "| Straight to goal | 1 |" in new
    log = []
    assert run(root, readme=readme, check=True, log=log.append, **FAST) == 0
    readme.write_text(re.sub(r"(\| Straight to goal \| 1 \| )\d\.\d{3}", r"\g<1>0.999", new))
    log.clear()
    assert run(root, readme=readme, check=True, log=log.append, **FAST) == 1
    assert "FAILED" in log[-1] and f"{readme}: [] row 'Straight to goal': differs" in log[-1]
    readme.write_text("no markers\n")
    assert run(root, readme=readme, log=log.append, **FAST) == 1 and "has no <!-- generated:results:start" in log[-1]
    # the CLI: a --root run leaves ./README.md and ./docs alone; the default root's run updates their blocks
    monkeypatch.chdir(tmp_path)
    readme.write_text(text)
    (tmp_path / "docs").mkdir()
    docs = tmp_path / "docs" / "results.md"
    docs_text = "# Results\n\n<!-- generated:docs-results:start -->\nold\n<!-- generated:docs-results:end -->\n"
    docs.write_text(docs_text)
    assert cli_main(["leaderboard", "--root", str(root), "--episodes", "1", "--scenes", "eth"]) == 0
    assert readme.read_text() == text and docs.read_text() == docs_text
    (tmp_path / "lb").rename(tmp_path / "leaderboard")
    assert cli_main(["leaderboard", "--episodes", "1", "--scenes", "eth"]) == 0
    assert "| Straight to goal | 1 |" in readme.read_text()
    new_docs = docs.read_text()
    assert "old" not in new_docs and "| Straight to goal | 1 |" in new_docs and "| straight | " in new_docs
    out = capsys.readouterr().out
    assert "the results block of README.md" in out and "the generated blocks of docs/results.md" in out
    assert cli_main(["leaderboard", "--check", "--episodes", "1", "--scenes", "eth"]) == 0
    docs.write_text(new_docs.replace("| straight | ", "| straight | 9"))
    assert cli_main(["leaderboard", "--check", "--episodes", "1", "--scenes", "eth"]) == 1
    assert "docs/results.md (docs-results): [Success rate] row 'straight': differs" in capsys.readouterr().out
    docs.write_text("no markers\n")
    assert cli_main(["leaderboard", "--docs", str(docs), "--episodes", "1", "--scenes", "eth"]) == 1
    assert "has no <!-- generated:docs-results:start" in capsys.readouterr().out


BOOM = '''
from examples.tiny_encoder import TinyEncoder


class Boom(TinyEncoder):  # passes the harness's 2-observation smoke test, fails on the real batch
    def forward(self, robot, humans=None, humans_mask=None):
        if robot.shape[0] > 2:
            raise RuntimeError("boom on a real batch")
        return super().forward(robot, humans, humans_mask)
'''


@pytest.mark.slow
def test_ray_fan_out_gives_the_sequential_numbers(tmp_path, monkeypatch):
    """--launcher ray: one Ray task per submission on a local 2-CPU cluster; the same results.json
    numbers as the sequential harness, and a task that fails rejects only its own submission."""
    import json
    import shutil

    pytest.importorskip("ray")
    monkeypatch.syspath_prepend(str(REPO))
    from examples.tiny_encoder import TinyEncoder

    base = tmp_path / "base"
    add_straight(base)
    add_toy(base)
    write_yaml(base, "orca", "name: orca\nkind: baseline\nentry: ORCA\npolicy: orca\nauthors: [a]\n")
    d = write_yaml(base, "boom", learned_yaml("boom", "boom", "encoder_import: boom_encoder:Boom\n")
                   .replace("Toy MLP", "Boom"))
    (d / "boom_encoder.py").write_text(BOOM)
    monkeypatch.setitem(ENCODERS, "boom", TinyEncoder)
    toy_checkpoint(d / "checkpoint.pt", {"name": "boom", "dim": 8})
    del ENCODERS["boom"]
    fast = {"episodes": 3, "scenes": ["hotel"], "tracks": ["v1"]}
    outs = {}
    for launcher in ("local", "ray"):
        root = tmp_path / launcher
        shutil.copytree(base, root)
        log = []
        jobs = 2 if launcher == "ray" else 1  # Ray: a 2-CPU local cluster; local: the sequential loop
        assert run(root, launcher=launcher, jobs=jobs, log=log.append, **fast) == 1, log  # boom is rejected ...
        (bad,) = [m for m in log if "error" in m]
        assert "submissions/boom/submission.yaml: evaluation failed: RuntimeError: boom on a real batch" in bad
        assert "\n" not in bad and "boom" in (root / "README.md").read_text().split("## Rejected")[1]
        outs[launcher] = {n: json.loads((root / "results" / n / "results.json").read_text())
                          for n in ("orca", "straight", "toy")}  # ... while the others are evaluated
    import ray

    assert not ray.is_initialized()  # the harness shut its cluster down
    for n, res in outs["local"].items():
        ray_res = outs["ray"][n]
        assert res["scenes"] == ray_res["scenes"] and res["episode_outcomes"] == ray_res["episode_outcomes"], n
        assert res["harness"]["fingerprint"] == ray_res["harness"]["fingerprint"]


def test_ray_that_cannot_start_is_one_line(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")

    def refuse(**kw):
        raise ConnectionError("could not connect\nto ray://nohost:10001")

    monkeypatch.setattr(ray, "init", refuse)
    root = tmp_path / "lb"
    add_straight(root)
    log = []
    assert run(root, launcher="ray", address="ray://nohost:10001", log=log.append, **FAST) == 1
    assert log[-1] == ("crowdbench leaderboard: error: --launcher ray: cannot join the Ray cluster at "
                       "ray://nohost:10001: ConnectionError: could not connect to ray://nohost:10001")
    assert not (root / "README.md").exists()  # nothing written


# ---------------------------------------------------------------------------------- hostile submissions
def table_columns(text: str) -> list[tuple[int, int]]:
    """``(header columns, row columns)`` of every row of every markdown table of ``text``
    (cells split on unescaped pipes)."""
    out, head = [], None
    for line in text.splitlines():
        if not line.startswith("|"):
            head = None
            continue
        n = len(re.split(r"(?<!\\)\|", line)) - 2
        head = n if head is None else head
        out.append((head, n))
    return out


def rejection(log: list[str], name: str) -> str:
    (line,) = [m for m in log if m.startswith("crowdbench leaderboard: error:") and f"/{name}/" in m]
    return line


def test_yaml_aliases_size_and_long_values_are_bounded(tmp_path):
    """Finding 5: aliases are refused (a 528-byte file used to expand to gigabytes in the error message,
    and a valid `authors: [&s ..., *s x1000]` to a 10 MB README), the file size and every list are bounded,
    and a wrongly typed value is cut short in the message."""
    import time

    from crowdbench.leaderboard import SubmissionError, read_submission

    root = tmp_path / "lb"
    add_straight(root)
    base = "name: {n}\nkind: baseline\npolicy: orca\nauthors: [a]\n"
    laughs = "".join(f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * 10) + "]\n" for i in range(1, 10))
    cases = {
        "laughs": "x: &l0 lol\n" + laughs + "seed: *l9\n",  # 9 levels of 10 aliases in a wrongly typed field
        "authors_alias": "name: authors_alias\nkind: baseline\npolicy: orca\n"
                         f"authors: [&s {'x' * 10_000}, " + ", ".join(["*s"] * 1000) + "]\n",
        "big": base.format(n="big") + "notes: " + "x" * 70_000 + "\n",  # over the size limit
        "many_authors": "name: many_authors\nkind: baseline\npolicy: orca\nauthors: [" + ", ".join(["a"] * 1000) + "]\n",
        "long_seed": base.format(n="long_seed") + "seed: " + "9" * 50_000 + "\n",  # an int too long to print
        "typed_seed": base.format(n="typed_seed") + "seed: [" + ", ".join(["abcdefgh"] * 3000) + "]\n",
        "deep": base.format(n="deep") + "overrides: " + "[" * 5000 + "]" * 5000 + "\n",
    }
    problems = {"laughs": "aliases", "authors_alias": "aliases", "big": "larger than 65536 bytes",
                "many_authors": "field 'authors': at most 20", "long_seed": "malformed YAML",
                "typed_seed": "field 'seed': must be an integer, got [", "deep": "nested deeper than"}
    for name, text in cases.items():
        d = write_yaml(root, name, text.replace("name: {n}", f"name: {name}"))
        t = time.process_time()  # CPU time: a bound on the parser's work, not on the machine's load
        with pytest.raises(SubmissionError) as e:
            read_submission(d)
        assert time.process_time() - t < 1, name
        msg = str(e.value)
        assert "\n" not in msg and len(msg) < 500 and problems[name] in msg, (name, msg[:300])
        assert msg.startswith(f"{d / 'submission.yaml'}: "), name
    assert "..." in str(pytest.raises(SubmissionError, read_submission, root / "submissions" / "typed_seed").value)
    log = []
    assert run(root, log=log.append, **FAST) == 1
    assert len((root / "README.md").read_text()) < 20_000 and len((root / "TRACKS.md").read_text()) < 20_000
    assert all(len(m) < 500 for m in log)


INJECTED = "Evil | World-best method | 1.000"


def test_markdown_injection_is_refused_or_escaped(tmp_path):
    """Finding 8: a newline in a one-line field is refused; pipes and markdown in submission text are
    escaped in every generated table (no forged row or column); links must be http(s) URLs with a host."""
    from crowdbench.leaderboard import SubmissionError, read_submission

    root = tmp_path / "lb"
    d = write_yaml(root, "evil", 'name: evil\nkind: baseline\npolicy: straight\nauthors: [a]\n'
                                 'entry: "Evil\\n| World-best method | 1.000 |"\n')
    with pytest.raises(SubmissionError, match=r"evil/submission.yaml: field 'entry': must be one line"):
        read_submission(d)
    for link, ok in (("javascript:alert(1)", False), ("data:text/html,<b>x</b>", False), ("docs/x.md", False),
                     ("https://", False), ("https://ex.org/a b", False), ("//ex.org/x", False),
                     ("https://ex.org/a|b", False), ("HTTPS://ex.org", False), ("https://ex.org/p?q=1#s", True),
                     ("http://ex.org:8080/a_b", True)):
        (d / "submission.yaml").write_text(f"name: evil\nkind: baseline\npolicy: straight\nauthors: [a]\n"
                                           f"link: {link!r}\n")
        if ok:
            assert read_submission(d).data["link"] == link
        else:
            with pytest.raises(SubmissionError, match=r"field 'link': must be an http:// or https:// URL"):
                read_submission(d)
    (d / "submission.yaml").write_text(f"name: evil\nkind: baseline\npolicy: straight\nentry: '{INJECTED} <b>[x](y)'\n"
                                       f"authors: ['x | 0.0 |', '*b* `c` _d_']\n")
    add_straight(root)
    assert run(root, log=lambda m: None, **FAST) == 0
    for f in ("README.md", "TRACKS.md"):
        text = (root / f).read_text()
        assert all(head == n for head, n in table_columns(text)), f
        assert not re.search(r"(?<!\\)\| World-best method", text) and "<b>" not in text
    readme = (root / "README.md").read_text()
    assert r"| Evil \| World-best method \| 1.000 \<b\>\[x\](y) | 1 |" in readme
    assert r"| x \| 0.0 \|, \*b\* \`c\` \_d\_ |" in readme


@pytest.mark.slow
def test_checkpoint_and_encoder_module_are_confined_to_the_submission(tmp_path):
    """Finding 10: `checkpoint:` and `encoder_import`'s module must be files inside the submission
    directory, reached without symlinks; the module is found without importing it."""
    import os
    import sys

    from crowdbench.leaderboard import SubmissionError, read_submission

    root = tmp_path / "lb"
    add_toy(root, "victim")
    outside = tmp_path / "secret.pt"
    outside.write_bytes(b"not a checkpoint")
    d = write_yaml(root, "thief", learned_yaml("thief"))
    (d / "real.pt").write_bytes(b"x")
    (d / "sub").mkdir()
    os.symlink(d / "real.pt", d / "link.pt")
    os.symlink(root / "submissions" / "victim", d / "vdir")
    for ckpt in ("../victim/checkpoint.pt", str(outside), str(d / "real.pt"), "link.pt", "vdir/checkpoint.pt",
                 "sub/../real.pt"):
        (d / "submission.yaml").write_text(learned_yaml("thief", extra=f"checkpoint: {ckpt}\n"))
        with pytest.raises(SubmissionError) as e:
            read_submission(d)
        assert str(e.value).startswith(f"{d / 'submission.yaml'}: field 'checkpoint': "), ckpt
        assert "inside the submission directory" in str(e.value) or "symlink" in str(e.value), ckpt
    (d / "submission.yaml").write_text(learned_yaml("thief", extra="checkpoint: real.pt\n"))
    assert read_submission(d).checkpoint == d / "real.pt"
    # the whole run: the thief is rejected, naming the field; nothing is evaluated for it
    (d / "submission.yaml").write_text(learned_yaml("thief", extra="checkpoint: ../victim/checkpoint.pt\n"))
    log = []
    assert run(root, log=log.append, **FAST) == 1
    assert "field 'checkpoint'" in rejection(log, "thief") and not (root / "results" / "thief").exists()
    # encoder modules: found statically (a module that raises at import is not run by read_submission)
    (d / "submission.yaml").write_text(learned_yaml("thief", "x_enc", "encoder_import: pkg.enc_mod:Enc\n"
                                                    "checkpoint: real.pt\n"))
    (d / "pkg").mkdir()
    (d / "pkg" / "enc_mod.py").write_text("raise SystemExit('imported')\n")
    assert read_submission(d).extra_files == [d / "pkg" / "enc_mod.py"] and "pkg.enc_mod" not in sys.modules
    (d / "pkg" / "enc_mod.py").unlink()
    (d / "pkg" / "enc_mod").mkdir()
    (d / "pkg" / "enc_mod" / "__init__.py").write_text("")
    assert read_submission(d).extra_files == [d / "pkg" / "enc_mod" / "__init__.py"]
    (d / "pkg" / "mine.py").symlink_to(REPO / "examples" / "tiny_encoder.py")
    for spec, problem in (("examples.tiny_encoder:TinyEncoder", "not a module file inside the submission directory"),
                          ("pkg.mine:TinyEncoder", "symlink"), ("os:system", "not a module file inside"),
                          ("../x:Y", "is not of the form module:Class")):
        (d / "submission.yaml").write_text(learned_yaml("thief", "x_enc", f"encoder_import: {spec!r}\n"
                                                        "checkpoint: real.pt\n"))
        with pytest.raises(SubmissionError, match=f"field 'encoder_import': .*{re.escape(problem)}"):
            read_submission(d)


TAGGED = '''
from examples.tiny_encoder import TinyEncoder


class Enc(TinyEncoder):
    TAG = {tag!r}
'''


def test_two_submissions_shipping_the_same_module_name_get_their_own(tmp_path, monkeypatch):
    """Finding 3: two submissions that both ship my_encoder.py are registered with their own class and
    fingerprinted with their own file (the sys.modules cache gave the second one the first one's)."""
    from crowdbench.leaderboard import fingerprint, read_submission
    from crowdbench.leaderboard.encoders import register_encoder

    monkeypatch.syspath_prepend(str(REPO))
    root = tmp_path / "lb"
    subs = []
    for tag in ("a", "b"):
        d = write_yaml(root, f"sub_{tag}", learned_yaml(f"sub_{tag}", f"enc_{tag}", "encoder_import: my_encoder:Enc\n"))
        (d / "my_encoder.py").write_text(TAGGED.format(tag=tag))
        toy_checkpoint(d / "checkpoint.pt", MLP)
        subs.append(read_submission(d))
    assert [s.extra_files for s in subs] == [[s.dir / "my_encoder.py"] for s in subs]
    assert fingerprint(subs[0], ["hotel"], 2) != fingerprint(subs[1], ["hotel"], 2)
    for s in subs:
        monkeypatch.delitem(ENCODERS, s.data["encoder"], raising=False)
        register_encoder(s)
        register_encoder(s)  # again (the harness registers in the job too): the same class, no conflict
    assert ENCODERS["enc_a"].TAG == "a" and ENCODERS["enc_b"].TAG == "b"
    assert [s.extra_files for s in subs] == [[s.dir / "my_encoder.py"] for s in subs]
    del ENCODERS["enc_a"], ENCODERS["enc_b"]


def make_run(tmp_path: Path) -> Path:
    from omegaconf import OmegaConf

    from crowdbench.cli import compose

    cfg = OmegaConf.to_container(compose(["encoder=mlp", "encoder.dim=8", "encoder.hidden=[16]", "seed=4"]),
                                 resolve=True)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    actor = build_actor("td3", dict(cfg["encoder"]), 1.0, squash=cfg["algo"]["actor_squash"])
    save_checkpoint(run_dir / "checkpoint.pt", {"config": cfg, "actor": actor.state_dict(), "frames": 640})
    return run_dir


def test_submit_validates_before_writing(tmp_path, capsys, monkeypatch):
    """Finding 11: `crowdbench submit --name ../../x` (or an absolute name, a bad link, a multi-line entry)
    is refused before anything is written; a failed read-back removes what was written."""
    import os

    run_dir = make_run(tmp_path)
    root = tmp_path / "a" / "b" / "lb"

    def files():
        return sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if "run" not in p.parts)

    before = files()
    for args, problem in ((["--name", "../../x"], "field 'name'"), (["--name", str(tmp_path / "abs")], "field 'name'"),
                          (["--name", "ok", "--link", "javascript:alert(1)"], "field 'link'"),
                          (["--name", "ok", "--entry", "Mine\n| forged | 1.000 |"], "field 'entry'"),
                          (["--name", "ok", "--authors", "a|b" * 100], "field 'authors'")):
        args = ["--entry", "Mine", *args] if "--entry" not in args else args
        assert cli_main(["submit", str(run_dir), *args, "--root", str(root)]) == 2, args
        err = capsys.readouterr().err.strip()
        assert problem in err and "\n" not in err and len(err) < 500, (args, err)
        assert files() == before, args  # nothing written, inside or outside the leaderboard
    from crowdbench.leaderboard import SubmissionError, submission

    def fail(sub_dir):
        raise SubmissionError(sub_dir / "submission.yaml", "checkpoint", "read back failed")

    monkeypatch.setattr(submission, "read_submission", fail)
    assert cli_main(["submit", str(run_dir), "--name", "ok", "--entry", "Mine", "--root", str(root)]) == 2
    assert "read back failed" in capsys.readouterr().err and not (root / "submissions" / "ok").exists()
    # directory names follow the same rule when the harness reads them
    monkeypatch.undo()
    d = write_yaml(root, "bad name", "name: bad name\nkind: baseline\npolicy: straight\nauthors: [a]\n")
    with pytest.raises(SubmissionError, match=r"field 'name': .*not a valid submission name"):
        submission.read_submission(d)
    os.rename(d, d.parent / "..x")
    with pytest.raises(SubmissionError, match=r"field 'name': .*not a valid submission name"):
        submission.read_submission(d.parent / "..x")


def test_a_corrupted_scene_file_is_one_line_and_writes_nothing(tmp_path, monkeypatch):
    """Finding 16: a corrupted or missing scene file stops the leaderboard with one line naming the file
    (exit 1), before anything is evaluated or written."""
    import shutil

    from crowdbench.data import scenes

    data = tmp_path / "eth_ucy"
    shutil.copytree(scenes.DATA_DIR, data)
    monkeypatch.setattr(scenes, "DATA_DIR", data)
    root = tmp_path / "lb"
    add_straight(root)
    for corrupt in (lambda p: p.write_text("garbage\n"), lambda p: p.unlink()):
        corrupt(data / "hotel.txt")
        log = []
        assert run(root, log=log.append, **FAST) == 1
        # (every run first says whether submitted code runs confined)
        assert len(log) == 2 and log[0].startswith("submitted code runs in worker processes"), log
        assert log[1].startswith(f"crowdbench leaderboard: error: {data / 'hotel.txt'}: "), log
        assert sorted(p.name for p in root.iterdir()) == ["submissions"]  # nothing written
