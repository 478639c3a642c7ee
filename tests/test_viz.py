"""Visualisation: rerun recordings read back with rerun's reader, attention == encoder gates, PNG figures
with content, training curves with seed bands, recording off = no viz/rerun code, one-line errors."""

import json
import shutil
import subprocess
import sys
from datetime import timedelta
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
import torch

from crowdbench.algos.actors import build_actor
from crowdbench.algos.checkpoint import LearnedPolicy, save_checkpoint
from crowdbench.baselines.straight import StraightToGoal
from crowdbench.cli import compose, main
from crowdbench.data.scenes import load_scene
from crowdbench.models.graph import Graph
from crowdbench.protocols.replay import evaluate

SCENE = "students003"


class Spy:
    """Wraps a policy and keeps every observation it was asked to act on (one per rollout step)."""

    def __init__(self, policy):
        self.policy, self.name, self.frame = policy, policy.name, policy.frame
        self.obs = []

    def reset(self, mask):
        self.policy.reset(mask)

    def act(self, td):
        self.obs.append(td.clone())
        return self.policy.act(td)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """An untrained MP-GatedGCN policy on 3 students003 episodes (ids 0, 124, 249), two recorded."""
    from crowdbench.viz.record import make_recorder_factory

    out = tmp_path_factory.mktemp("rec")
    torch.manual_seed(0)
    actor = build_actor("td3", {"name": "gatedgcn", "dim": 16}, 1.0)
    spy = Spy(LearnedPolicy(actor, name="tiny-gatedgcn"))
    cfg = compose(["viz.record=true", "viz.episodes=[0,124]", "eval.episodes=3", f"eval.scenes=[{SCENE}]"])
    factory = make_recorder_factory(spy.policy, cfg, out, [SCENE])
    evaluate(spy, [SCENE], 3, out_dir=out, save_episodes=True, recorder_factory=factory)
    rows = {r["episode"]: r for r in map(json.loads, (out / "episodes.jsonl").read_text().splitlines())}
    return out, spy, rows, actor.module.encoder


def test_recording_readable_with_entities_and_steps(recorded):
    from crowdbench.viz.record import ENTITIES, read_recording

    out, _, rows, _ = recorded
    files = sorted(p.name for p in (out / "recordings").glob("*.rrd"))
    assert files == [f"{SCENE}_ep000.rrd", f"{SCENE}_ep124.rrd"]  # episode 249 was not asked for
    scene = load_scene(SCENE, 0.25, "true")
    for ep in (0, 124):
        rec = read_recording(out / "recordings" / f"{SCENE}_ep{ep:03d}.rrd")
        row = rows[ep]
        assert set(ENTITIES) <= set(rec)
        robot = [r for r in rec["world/robot"] if r["step"] is not None]
        n = len(row["robot_xy"])  # steps + 1 positions
        assert [r["step"] for r in robot] == list(range(n))
        assert all(r["time"] == timedelta(seconds=r["step"] * 0.25) for r in robot)
        xy = np.array([r["Points2D:positions"][0] for r in robot])
        assert np.allclose(xy, row["robot_xy"], atol=1e-4)  # same path as episodes.jsonl
        assert len(rec["scalars/reward"]) == n - 1 and len(rec["scalars/speed"]) == n - 1
        assert rec["events"][-1]["TextLog:text"][0].startswith(row["outcome"])
        # humans carry their ids: exactly the pedestrians present at that grid step of the scene
        t0 = round(row["start_time_s"] / 0.25)
        for r in rec["world/humans"][:: max(1, n // 5)]:
            t = t0 + r["step"]
            expect = sorted(scene.ped_id[t][scene.valid[t]].tolist())
            assert sorted(r["ped_id"]) == expect == sorted(int(s) for s in r["Points2D:labels"])
        for r in rec["scalars/min_clearance"]:  # surface gap to the nearest present human, capped at 5 m
            t = t0 + r["step"]
            h = scene.pos[t][scene.valid[t]].double()
            gap = ((h - torch.tensor(row["robot_xy"][r["step"]]).double()).norm(dim=-1).min() - 0.3).item()
            assert abs(r["Scalars:scalars"][0] - min(gap, 5.0)) < 1e-3
        goal = rec["world/goal"][0]["Points2D:positions"][0]
        assert np.allclose(goal, row["goal"], atol=1e-4)


def test_attention_in_recording_equals_encoder_gates(recorded):
    """Recompute the last layer's gates from the step's observation (gates_out of encode, not
    last_gates) and compare with the values, neighbours, widths and labels stored in the recording."""
    from crowdbench.viz.record import ATTN_WIDTH, read_recording

    out, spy, rows, encoder = recorded
    checked = multi = 0
    for b, ep in ((0, 0), (1, 124)):
        att = [r for r in read_recording(out / "recordings" / f"{SCENE}_ep{ep:03d}.rrd")["world/attention"]
               if "gate" in r]
        n_steps = len(rows[ep]["robot_xy"]) - 1
        assert [r["step"] for r in att] == list(range(n_steps))
        for r in att:
            td = spy.obs[r["step"]]
            g = encoder.build_graph(td)
            gates = []
            with torch.no_grad():
                encoder.encode(g, gates_out=gates)
            eta = gates[-1][b, 0].mean(-1)  # robot row, [K+1]; (B, A=1) flattened
            nbr, mask, _ = Graph.slots(g)
            nbr, mask = nbr[b, 0], mask[b, 0]
            expect = eta[mask].double().numpy()
            assert r["node"] == nbr[mask].tolist()
            assert np.allclose(r["gate"], expect, atol=1e-6)
            assert abs(sum(r["gate"]) - 1.0) < 1e-3
            assert np.allclose(r["LineStrips2D:radii"], ATTN_WIDTH * expect, atol=1e-6)
            assert r["LineStrips2D:labels"] == [f"{v:.2f}" for v in r["gate"]]
            m = td["agents", "observation", "humans_mask"][b, 0]
            assert len(r["gate"]) == 1 + min(int(m.sum()), encoder.k) or len(r["gate"]) <= 1 + encoder.k
            checked += 1
            multi += len(r["gate"]) >= 3
    assert checked > 10 and multi > 0  # some steps have the goal and at least two humans


@pytest.mark.slow
def test_cli_eval_records_and_run_dir_layout(tmp_path, capsys):
    """`crowdbench eval ... viz.record=true` with a policy without gates: recordings, no attention entity."""
    rc = main(["eval", "policy=straight", "eval.scenes=[hotel]", "eval.episodes=2", "viz.record=true",
               "viz.episodes=[0]", f"out={tmp_path}"])
    assert rc == 0
    from crowdbench.viz.record import read_recording

    path = tmp_path / "recordings" / "hotel_ep000.rrd"
    rec = read_recording(path)
    assert "world/robot" in rec and "world/attention" not in rec
    viewer = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if viewer:  # the viewer's own loader accepts the file (schema and archetypes checked)
        proc = subprocess.run([viewer, "rrd", "verify", str(path)], check=False, capture_output=True, text=True,
                              timeout=120)
        assert proc.returncode == 0 and "verified without error" in proc.stdout + proc.stderr


def test_recording_off_runs_no_viz_code(tmp_path, monkeypatch):
    """Default (viz.record=false): no viz module and no rerun is even imported, nothing is recorded.
    Blocking the imports makes any attempt fail; with viz.record=true the same setup does fail."""
    for mod in ("rerun", "crowdbench.viz", "crowdbench.viz.record", "crowdbench.viz.figures"):
        monkeypatch.setitem(sys.modules, mod, None)  # `import mod` now raises ImportError
    args = ["eval", "policy=straight", "eval.scenes=[hotel]", "eval.episodes=2"]
    assert main([*args, f"out={tmp_path}"]) == 0
    assert (tmp_path / "results.json").exists() and not (tmp_path / "recordings").exists()
    with pytest.raises(ImportError):
        main([*args, "viz.record=true", f"out={tmp_path / 'on'}"])
    # the recorder hook is the only entry point: evaluate calls the factory once per scene, if given
    calls = []
    evaluate(StraightToGoal(), ["hotel"], 2, recorder_factory=lambda s: calls.append(s))
    assert calls == ["hotel"]


def non_trivial_png(path):
    img = mpimg.imread(path)[..., :3]
    assert img.shape[0] > 200 and img.shape[1] > 200
    assert img.std() > 0.05
    assert (img.min(-1) < 0.9).mean() > 0.02  # more than a few non-white pixels
    return img


def test_viz_png_episode_and_grid(tmp_path, capsys):
    evaluate(StraightToGoal(), ["hotel", SCENE], 4, out_dir=tmp_path, save_episodes=True)
    assert main(["viz", str(tmp_path), "--scene", SCENE, "--episode", "83"]) == 0
    png = tmp_path / "viz" / f"{SCENE}_ep083.png"
    img = non_trivial_png(png)
    robot = np.array([0x1F, 0x5F, 0xD0]) / 255  # the robot's path colour is drawn
    assert (np.abs(img - robot).max(-1) < 0.05).sum() > 100
    assert main(["viz", str(tmp_path / "episodes.jsonl"), "--grid", "4", "--out", str(tmp_path / "g.png")]) == 0
    non_trivial_png(tmp_path / "g.png")  # the first scene of the file: hotel
    assert "wrote" in capsys.readouterr().out


def test_figures_equal_scales_and_a_legend_for_humans(tmp_path, monkeypatch):
    """A grid shows every episode at one scale (same metres per panel) and time colour; the figures'
    legends name the humans' paths; the PNG is cropped to its content."""
    from crowdbench.viz import figures

    evaluate(StraightToGoal(), [SCENE], 4, out_dir=tmp_path, save_episodes=True)
    rows = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    figs = []
    real_save = figures._save
    monkeypatch.setattr(figures, "_save", lambda fig, out, **kw: (figs.append(fig), real_save(fig, out, **kw))[1])
    figures.grid_figure(rows, tmp_path / "grid.png")
    panels = [ax for ax in figs[0].axes if ax.get_title().startswith(SCENE)]
    assert len(panels) == 4
    sizes = {(round(np.diff(ax.get_xlim())[0], 6), round(np.diff(ax.get_ylim())[0], 6)) for ax in panels}
    assert len(sizes) == 1  # equal scales
    assert any("human within sensing range" in t.get_text() for lg in figs[0].legends for t in lg.get_texts())
    figures.episode_figure(rows[0], tmp_path / "ep.png")
    texts = [t.get_text() for t in figs[1].axes[0].get_legend().get_texts()]
    assert {"start", "goal", "human within sensing range", "human out of range"} <= set(texts)
    img = non_trivial_png(tmp_path / "ep.png")
    for blank in ((img.min(-1) > 0.99).all(1), (img.min(-1) > 0.99).all(0)):  # rows, columns
        ink = np.nonzero(~blank)[0]
        assert ink[0] < 12 and len(blank) - 1 - ink[-1] < 12  # blank margins under 0.1 in (120 dpi)


@pytest.mark.slow  # the README's viz --video command is the quick suite's video test
def test_viz_video_one_frame_per_step(tmp_path, monkeypatch, capsys):
    """`viz --video FILE.gif`: as many frames as the episode has steps, drawn (not blank); an MP4 without
    ffmpeg is a one-line error naming it, written by nothing."""
    from matplotlib import animation
    from PIL import Image

    evaluate(StraightToGoal(), ["hotel"], 3, out_dir=tmp_path, save_episodes=True)
    rows = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    row = rows[1]
    assert main(["viz", str(tmp_path), "--episode", str(row["episode"]), "--video", str(tmp_path / "ep.gif")]) == 0
    with Image.open(tmp_path / "ep.gif") as gif:
        assert gif.n_frames == len(row["robot_xy"]) - 1 > 5  # one frame per step
        assert gif.info["duration"] == 250  # real time: dt = 0.25 s per frame
        first = np.asarray(gif.convert("RGB"))
        gif.seek(gif.n_frames - 1)
        last = np.asarray(gif.convert("RGB"))
    assert first.std() > 10 and np.abs(first.astype(int) - last).sum() > 0  # the robot moved between them
    assert main(["viz", str(tmp_path), "--video", str(tmp_path / "fast.gif"), "--fps", "10"]) == 0
    with Image.open(tmp_path / "fast.gif") as gif:
        assert gif.n_frames == len(rows[0]["robot_xy"]) - 1 and gif.info["duration"] == 100
    capsys.readouterr()
    monkeypatch.setattr(animation.writers, "is_available", lambda name: False)
    assert main(["viz", str(tmp_path), "--video", str(tmp_path / "ep.mp4")]) == 2
    err = capsys.readouterr().err
    assert "needs ffmpeg" in err and err.count("\n") == 1 and not (tmp_path / "ep.mp4").exists()


@pytest.mark.slow
def test_viz_video_mp4_frame_count(tmp_path):
    from conftest import require_system

    require_system("ffmpeg")
    require_system("ffprobe")
    evaluate(StraightToGoal(), ["hotel"], 2, out_dir=tmp_path, save_episodes=True)
    row = json.loads((tmp_path / "episodes.jsonl").read_text().splitlines()[0])
    assert main(["viz", str(tmp_path), "--video", str(tmp_path / "ep.mp4")]) == 0
    probe = subprocess.run(["ffprobe", "-v", "error", "-count_frames", "-select_streams", "v:0", "-show_entries",
                            "stream=nb_read_frames", "-of", "csv=p=0", str(tmp_path / "ep.mp4")],
                           capture_output=True, text=True, check=True)
    assert int(probe.stdout.strip()) == len(row["robot_xy"]) - 1


def fake_run(root, name, seed, frames, success, config_extra=None):
    """A run directory as `crowdbench run` leaves it: TorchRL CSVLogger scalars + a checkpoint config."""
    from torchrl.record.loggers.csv import CSVLogger

    run = root / name
    logger = CSVLogger(exp_name="logs", log_dir=str(run))
    for f, s in zip(frames, success, strict=True):
        logger.log_scalar("success_rate", s, step=f)
        logger.log_scalar("episode_return", s - 0.4, step=f)
        logger.log_scalar("loss_critic", 1.0 / (1 + f), step=f)
    config = {"seed": seed, "out": str(run), "algo": {"name": "td3"}, "encoder": {"name": "gatedgcn", "dim": 32},
              **(config_extra or {})}
    save_checkpoint(run / "checkpoint.pt", {"config": config, "actor": {}, "frames": frames[-1]})
    return run


def test_plot_overlays_runs_with_seed_band(tmp_path):
    from crowdbench.viz.curves import band, group_runs, read_scalars

    a = fake_run(tmp_path, "s0", 0, [256, 512, 768, 1024], [0.0, 0.2, 0.4, 0.6])
    b = fake_run(tmp_path, "s1", 1, [256, 512, 768], [0.2, 0.2, 0.6])
    c = fake_run(tmp_path, "gcn", 0, [256, 512], [0.1, 0.3], {"encoder": {"name": "gcn", "dim": 32}})
    logs = read_scalars(a)
    assert logs["success_rate"].tolist() == [[256, 0.0], [512, 0.2], [768, 0.4], [1024, 0.6]]
    groups = group_runs([a, b, c])
    assert [len(m) for _, m in groups] == [2, 1]
    assert "2 seeds" in groups[0][0] and "encoder.name=gcn" not in groups[0][0]
    x, mean, lo, hi = band([read_scalars(a)["success_rate"], read_scalars(b)["success_rate"]], 1)
    assert x.tolist() == [256, 512, 768]  # the overlap of the two runs
    assert np.allclose(mean, [0.1, 0.2, 0.5]) and np.allclose(lo, [0.0, 0.2, 0.4]) and np.allclose(hi, [0.2, 0.2, 0.6])
    assert main(["plot", str(a), str(b), str(c), "--out", str(tmp_path / "curves.png")]) == 0
    non_trivial_png(tmp_path / "curves.png")
    from crowdbench.viz import curves

    figs = []
    real_save = curves._save
    curves._save = lambda fig, out, **kw: (figs.append(fig), real_save(fig, out, **kw))[1]
    try:
        curves.plot_runs([a, b, c], tmp_path / "grid.png")
    finally:
        curves._save = real_save
    drawn = [ax for ax in figs[0].axes if ax.get_title()]
    assert len(drawn) == 3 and len({round(ax.get_position().x0, 3) for ax in drawn}) == 2  # two columns, not a strip
    colours = [ln.get_color() for ln in drawn[0].get_lines()]
    assert len(set(colours)) == 2  # one colour per group of runs
    assert main(["plot", str(a)]) == 0 and (a / "curves.png").exists()


@pytest.mark.parametrize("args, message", [
    (["viz", "{tmp}/missing.jsonl"], "no such file or directory:"),
    (["viz", "{tmp}"], "no episodes.jsonl in"),
    (["viz", "{tmp}/ev", "--episode", "250"], "episode 250 not in"),
    (["viz", "{tmp}/ev", "--scene", "eth"], "scene 'eth' not in"),
    (["viz", "{tmp}/ev", "--episode", "x"], "invalid int value: 'x'"),
    (["viz", "{tmp}/ev", "--grid", "0"], "--grid must be >= 1"),
    (["viz", "{tmp}/ev", "--video", "{tmp}/ep.avi"], "the file must end in .gif or .mp4"),
    (["viz", "{tmp}/ev", "--video", "{tmp}/ep.gif", "--grid", "2"], "--video FILE animates one episode"),
    (["viz", "{tmp}/ev", "--video", "{tmp}/ep.gif", "--fps", "0"], "--fps must be in (0, 100]"),
    (["plot", "{tmp}"], "no training log in"),
    (["plot", "{tmp}/nope"], "run directory not found:"),
    (["eval", "policy=straight", "eval.scenes=[hotel]", "eval.episodes=2", "viz.record=true", "viz.episodes=[7]"],
     "viz.episodes: episode 7 is not evaluated on hotel"),
    (["eval", "policy=straight", "eval.scenes=[hotel]", "viz.record=true", "viz.scenes=[eth]"],
     "viz.scenes: scene 'eth' is not evaluated"),
    # a training run checks viz.* before it trains (not after 30 minutes)
    (["run", "eval.scenes=[hotel]", "eval.episodes=2", "viz.record=true", "viz.episodes=[0,7]"],
     "viz.episodes: episode 7 is not evaluated on hotel"),
])
def test_bad_input_one_line_error(args, message, tmp_path, capsys):
    (tmp_path / "ev").mkdir()
    (tmp_path / "ev" / "episodes.jsonl").write_text(json.dumps({
        "scene": "hotel", "episode": 0, "start_time_s": 0.0, "dt": 0.25, "start": [0, 0], "goal": [1, 1],
        "robot_xy": [[0, 0], [0.2, 0.2]], "outcome": "timeout"}) + "\n")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    if args[0] in ("eval", "run"):
        args.append(f"out={tmp_path / 'out'}")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists() and not list(tmp_path.rglob("*.png")) and not list(tmp_path.rglob("*.gif"))
