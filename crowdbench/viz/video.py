"""One recorded episode as a video (``crowdbench viz OUT --video FILE.gif|FILE.mp4``): a matplotlib
animation with one frame per simulation step, frame ``k`` (1..steps) the state after step ``k``: the
robot (its body to scale) with its path so far, the humans present at that step (bodies to scale, a
short trail each), every human's whole path in the episode faintly, start and goal. Humans come from
the scene data as in the static figure (crowdbench/viz/figures.py). A GIF needs only Pillow (a
matplotlib dependency); an MP4 needs ``ffmpeg`` on the ``PATH``. Played at real time by default
(``1 / dt`` frames per second).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import animation
from matplotlib.patches import Circle

from crowdbench.viz.figures import GOAL, ROBOT, human_paths

HUMAN = "#e07b00"
TRAIL_STEPS = 8  # a human's trail: its last 2 s at dt = 0.25
FORMATS = (".gif", ".mp4")


def writer(out: Path, fps: float):
    """The matplotlib writer for ``out``'s suffix; ``ValueError`` (one line) for another suffix or an
    MP4 without ffmpeg."""
    suffix = out.suffix.lower()
    if suffix == ".gif":
        return animation.PillowWriter(fps=fps)
    if suffix == ".mp4":
        if not animation.writers.is_available("ffmpeg"):
            raise ValueError(f"--video {out}: an MP4 needs ffmpeg on the PATH (not found); install ffmpeg or "
                             "write a .gif")
        return animation.FFMpegWriter(fps=fps, codec="h264", extra_args=["-pix_fmt", "yuv420p"])
    raise ValueError(f"--video {out}: the file must end in {' or '.join(FORMATS)}")


def _frame_data(row: dict, time_base: str):
    from crowdbench.data.scenes import load_scene

    dt = float(row["dt"])
    xy = np.asarray(row["robot_xy"], dtype=float)
    n = len(xy) - 1
    scene = load_scene(row["scene"], dt, time_base)
    return dt, xy, n, human_paths(scene, round(row["start_time_s"] / dt), n)


def _axes(row: dict, xy: np.ndarray, humans: dict, size: float):
    span = np.vstack([xy, [row["start"], row["goal"]]])
    lo, hi = span.min(0) - 2.0, span.max(0) + 2.0
    extent = np.maximum(hi - lo, 0.6 * (hi - lo).max())  # not a thin strip: room for the crowd beside the path
    mid = (lo + hi) / 2
    lo, hi = mid - extent / 2, mid + extent / 2
    w, h = extent
    fig, ax = plt.subplots(figsize=(size, min(max(size * h / w, 3.0), 2 * size)))
    for k, p in humans.values():
        ax.plot(p[:, 0], p[:, 1], color=HUMAN, lw=0.6, alpha=0.18)
    ax.plot(*row["start"], "s", color=ROBOT, ms=7, label="start")
    ax.plot(*row["goal"], "*", color=GOAL, ms=13, label="goal")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    ax.set_xlabel("x (m)", fontsize=8)
    ax.set_ylabel("y (m)", fontsize=8)
    return fig, ax


def episode_video(row: dict, out: Path, time_base: str = "true", fps: float | None = None, size: float = 5.0,
                  dpi: int = 80, robot_radius: float = 0.2, human_radius: float = 0.1) -> tuple[Path, int]:
    """Write the animation of episode record ``row`` to ``out`` (.gif or .mp4); returns it and its frames."""
    out = Path(out)
    dt, xy, n, humans = _frame_data(row, time_base)
    if n < 1:
        raise ValueError(f"episode {row['episode']} of {row['scene']} has no step to animate")
    w = writer(out, fps or 1.0 / dt)
    fig, ax = _axes(row, xy, humans, size)
    (path,) = ax.plot([], [], color=ROBOT, lw=1.6, label="robot")
    robot = ax.add_patch(Circle(xy[0], robot_radius, facecolor=ROBOT, edgecolor="black", lw=0.6, zorder=5))
    bodies = {pid: ax.add_patch(Circle((0, 0), human_radius, color=HUMAN, zorder=4, visible=False)) for pid in humans}
    trails = {pid: ax.plot([], [], color=HUMAN, lw=0.9, alpha=0.7)[0] for pid in humans}
    ax.plot([], [], "o", color=HUMAN, ms=5, label="humans")  # the legend's entry for the bodies
    ax.legend(fontsize=7, loc="upper right", framealpha=0.8)
    label = f"{row['scene']} episode {row['episode']}"
    title = ax.set_title(f"{label}, t = 0.00 s: {row['outcome']}", fontsize=9)  # the layout makes room for it

    def draw(k: int):
        path.set_data(xy[: k + 1, 0], xy[: k + 1, 1])
        robot.set_center(xy[k])
        for pid, (steps, p) in humans.items():
            now = steps == k
            bodies[pid].set_visible(bool(now.any()))
            if now.any():
                bodies[pid].set_center(p[now][0])
            recent = (steps <= k) & (steps > k - TRAIL_STEPS)
            trails[pid].set_data(p[recent, 0], p[recent, 1])
        end = f": {row['outcome']}" if k == n else ""
        title.set_text(f"{label}, t = {k * dt:.2f} s{end}")
        return [path, robot, title, *bodies.values(), *trails.values()]

    anim = animation.FuncAnimation(fig, draw, frames=range(1, n + 1), blit=False, repeat=False)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout(pad=0.4)
    try:
        anim.save(out, writer=w, dpi=dpi)
    finally:
        plt.close(fig)
    return out, n
