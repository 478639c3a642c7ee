"""``crowdbench viz`` and ``crowdbench plot``: their arguments, then a figure (crowdbench/viz/figures.py), a
video (video.py) or training curves (curves.py)."""

from __future__ import annotations

from pathlib import Path

from crowdbench.outputs import check_writable_file
from crowdbench.viz.figures import _Parser, episode_figure, grid_figure, pick_episode, pick_scene
from crowdbench.viz.records import load_rows


def viz_command(argv: list[str]) -> Path:
    p = _Parser(prog="crowdbench viz", description="A figure (paper Fig. 6 style) or a video of recorded episodes.")
    p.add_argument("path", help="an episodes.jsonl, or the results directory holding it (eval.save_episodes=true)")
    p.add_argument("--episode", type=int, default=None, help="episode id (default: the scene's first)")
    p.add_argument("--scene", default=None, help="scene (default: the file's first)")
    p.add_argument("--grid", type=int, default=None, metavar="K", help="the scene's first K episodes in one figure")
    p.add_argument("--mark-every", type=float, default=2.0, metavar="S", help="time marks every S seconds")
    p.add_argument("--out", default=None, metavar="FILE.png", help="default: <results dir>/viz/<scene>_ep<id>.png")
    p.add_argument("--video", default=None, metavar="FILE.gif|FILE.mp4",
                   help="the episode animated instead, one frame per step (MP4: needs ffmpeg)")
    p.add_argument("--fps", type=float, default=None, help="the video's frames per second (default: real time)")
    a = p.parse_args(argv)
    if a.grid is not None and a.grid < 1:
        raise ValueError(f"--grid must be >= 1, got {a.grid}")
    if a.mark_every <= 0:
        raise ValueError(f"--mark-every must be > 0 s, got {a.mark_every}")
    if a.video is not None and (a.grid is not None or a.out is not None):
        raise ValueError("--video FILE animates one episode: without --grid and --out")
    if a.fps is not None and not (a.video and 0 < a.fps <= 100):
        raise ValueError(f"--fps must be in (0, 100] and goes with --video, got {a.fps}")
    if a.video is not None:
        from crowdbench.viz.video import writer

        writer(Path(a.video), 1.0)  # a bad suffix or a missing ffmpeg fails before any work
        check_writable_file(Path(a.video))
    rows, path, time_base = load_rows(Path(a.path))
    scene, rows = pick_scene(rows, a.scene, path)
    if a.grid is not None:
        out = Path(a.out) if a.out else path.parent / "viz" / f"{scene}_grid{a.grid}.png"
        check_writable_file(out)
        return grid_figure(rows[: a.grid], out, time_base, a.mark_every)
    row = rows[0] if a.episode is None else pick_episode(rows, a.episode, scene, path)
    if a.video is not None:
        from crowdbench.viz.video import episode_video

        return episode_video(row, Path(a.video), time_base, a.fps)[0]
    out = Path(a.out) if a.out else path.parent / "viz" / f"{scene}_ep{row['episode']:03d}.png"
    check_writable_file(out)
    return episode_figure(row, out, time_base, a.mark_every)


def main(command: str, argv: list[str]) -> int:
    if command == "plot":
        from crowdbench.viz.curves import plot_command

        out = plot_command(argv)
    else:
        out = viz_command(argv)
    print(f"wrote {out}")
    return 0
