"""Static figures with matplotlib (Agg, headless): episode trajectories (the commands: crowdbench/viz/commands.py).

- ``crowdbench viz <episodes.jsonl | results dir> [--episode N] [--scene S] [--grid K] [--out FILE]``:
  one episode in the style of the paper's Fig. 6 (robot path, start, goal, the humans' paths over
  the episode, markers every ``--mark-every`` seconds coloured by time, the robot's body to scale
  at those times, labelled in seconds), or a grid of the first ``K`` episodes of a scene. Humans'
  paths come from the scene data (the same resampled replay the simulator used): the episode
  starts at grid step ``start_time_s / dt`` and lasts ``len(robot_xy) - 1`` steps. Humans that
  never come within the sensing range of the robot are drawn faintly, without markers.
- ``crowdbench viz ... --video FILE.gif|FILE.mp4``: the episode animated, one frame per step
  (crowdbench/viz/video.py).
- ``crowdbench plot``: training curves (crowdbench/viz/curves.py).

Bad input (missing file, no such episode or scene) raises ``ValueError`` with a one-line message; the
CLI prints it and exits with code 2.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

ROBOT = "#1f5fd0"
GOAL = "#d62728"
TIME_CMAP = "viridis"


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage dump, no SystemExit
        raise ValueError(f"{self.prog}: {message}")


# ---------------------------------------------------------------------------------------------- episodes
def _ranges(ids: list[int]) -> str:
    ids = sorted(ids)
    if ids == list(range(ids[0], ids[-1] + 1)):
        return f"{ids[0]}..{ids[-1]}"
    return ", ".join(map(str, ids[:10])) + (", ..." if len(ids) > 10 else "")


def pick_scene(rows: list[dict], scene: str | None, path: Path) -> tuple[str, list[dict]]:
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    scene = scene or scenes[0]
    if scene not in scenes:
        raise ValueError(f"scene {scene!r} not in {path} (scenes: {', '.join(scenes)})")
    return scene, [r for r in rows if r["scene"] == scene]


def pick_episode(rows: list[dict], episode: int, scene: str, path: Path) -> dict:
    for r in rows:
        if r["episode"] == episode:
            return r
    raise ValueError(f"episode {episode} not in {path} for {scene} "
                     f"(episodes available: {_ranges([r['episode'] for r in rows])})")


def human_paths(scene, t0: int, n: int) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``{ped_id: (steps [k], positions [k, 2])}`` of the humans present during steps ``t0..t0+n``
    (``steps`` relative to the episode start)."""
    t1 = min(t0 + n, scene.n_steps - 1)
    ids = scene.ped_id[t0 : t1 + 1].numpy()
    valid = scene.valid[t0 : t1 + 1].numpy()
    pos = scene.pos[t0 : t1 + 1].numpy()
    out = {}
    for pid in np.unique(ids[valid]):
        k, m = np.nonzero((ids == pid) & valid)
        out[int(pid)] = (k, pos[k, m])
    return out


def extent(row: dict, margin: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """The centre and the size (m) of the area an episode's figure shows: its path, start and goal, plus
    ``margin`` on every side."""
    span = np.vstack([np.asarray(row["robot_xy"], dtype=float), [row["start"], row["goal"]]])
    lo, hi = span.min(0) - margin, span.max(0) + margin
    return (lo + hi) / 2, hi - lo


def legend_handles(collision: bool) -> list:
    """The legend's entries: the robot, start, goal and both kinds of human path."""
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=ROBOT, lw=1.8, marker="o", mfc="white", ms=5, label="robot (body at time marks)"),
               Line2D([], [], color=ROBOT, marker="s", ls="", ms=6, label="start"),
               Line2D([], [], color=GOAL, marker="*", ls="", ms=10, label="goal"),
               Line2D([], [], color="0.35", lw=0.9, marker="o", mfc="0.55", mec="none", ms=4,
                      label="human within sensing range"),
               Line2D([], [], color="0.6", lw=0.6, alpha=0.4, label="human out of range")]
    if collision:
        handles.append(Line2D([], [], color=GOAL, marker="x", ls="", ms=8, mew=2, label="collision"))
    return handles


def draw_episode(ax, row: dict, time_base: str = "true", mark_every_s: float = 2.0, sensing_range: float = 5.0,
                 robot_radius: float = 0.2, human_radius: float = 0.1, legend: bool = True, labels: bool = True,
                 size: np.ndarray | None = None, norm=None):
    """Draw one episode record on ``ax`` (Fig. 6 style); returns the time colour normaliser. ``size``: the
    width and height (m) shown around the episode's centre (a grid passes one size: equal scales);
    ``norm``: the time colours (a grid passes one: equal colours)."""
    from matplotlib import patheffects
    from matplotlib.patches import Circle

    from crowdbench.data.scenes import load_scene

    dt = float(row["dt"])
    scene = load_scene(row["scene"], dt, time_base)
    xy = np.asarray(row["robot_xy"], dtype=float)
    n = len(xy) - 1
    t0 = round(row["start_time_s"] / dt)
    norm = norm or plt.Normalize(0.0, max(n * dt, dt))
    cmap = matplotlib.colormaps[TIME_CMAP]
    every = max(1, round(mark_every_s / dt))
    marks = sorted(set(range(0, n + 1, every)) | {n})
    halo = [patheffects.withStroke(linewidth=2.2, foreground="white")]  # readable over the paths

    for pid, (k, p) in human_paths(scene, t0, n).items():
        near = np.linalg.norm(p - xy[np.minimum(k, n)], axis=1).min() <= sensing_range
        if not near:
            ax.plot(p[:, 0], p[:, 1], color="0.6", lw=0.6, alpha=0.25)
            continue
        ax.plot(p[:, 0], p[:, 1], color="0.35", lw=0.9, alpha=0.8)
        sel = np.isin(k, marks)
        for kk, pp in zip(k[sel], p[sel], strict=True):
            ax.add_patch(Circle(pp, human_radius, color=cmap(norm(kk * dt)), alpha=0.9, lw=0))
        if labels:
            ax.annotate(str(pid), p[0], fontsize=7, color="0.2", xytext=(2, 2), textcoords="offset points",
                        path_effects=halo)

    ax.plot(xy[:, 0], xy[:, 1], color=ROBOT, lw=1.8, zorder=3)
    for k in marks:
        ax.add_patch(Circle(xy[k], robot_radius, facecolor=cmap(norm(k * dt)), edgecolor=ROBOT, lw=1.0, zorder=4))
        if labels:
            ax.annotate(f"{k * dt:g}", xy[k], fontsize=7, color=ROBOT, xytext=(4, -9), textcoords="offset points",
                        zorder=5, path_effects=halo)
    ax.plot(*row["start"], "s", color=ROBOT, ms=7, zorder=5)
    ax.plot(*row["goal"], "*", color=GOAL, ms=14, zorder=5)
    if row["outcome"] == "collision":
        ax.plot(*xy[-1], "x", color=GOAL, ms=11, mew=2.5, zorder=6)
    ax.set_aspect("equal")
    centre, own = extent(row)
    size = own if size is None else np.asarray(size)
    ax.set_xlim(centre[0] - size[0] / 2, centre[0] + size[0] / 2)
    ax.set_ylim(centre[1] - size[1] / 2, centre[1] + size[1] / 2)
    nav = f", {row['nav_time_s']:.2f} s" if row.get("nav_time_s") is not None else ""
    ax.set_title(f"{row['scene']} episode {row['episode']}: {row['outcome']}{nav}", fontsize=9)
    if legend:
        ax.legend(handles=legend_handles(row["outcome"] == "collision"), fontsize=7, loc="best", framealpha=0.85)
    return norm


def episode_figure(row: dict, out: Path, time_base: str = "true", mark_every_s: float = 2.0) -> Path:
    _, (w, h) = extent(row)
    fig, ax = plt.subplots(figsize=(7.0, min(max(6.0 * h / w, 3.5), 9.0)), layout="constrained")  # the path's extent
    norm = draw_episode(ax, row, time_base, mark_every_s)
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=TIME_CMAP), ax=ax, label="time since start (s)",
                 fraction=0.04, pad=0.02)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return _save(fig, out)


def grid_figure(rows: list[dict], out: Path, time_base: str = "true", mark_every_s: float = 2.0) -> Path:
    """The episodes side by side at one scale (every panel shows the same width and height in metres) and
    with one time colour scale, one legend and one colour bar for all."""
    cols = math.ceil(math.sqrt(len(rows)))
    nrows = math.ceil(len(rows) / cols)
    size = np.max([extent(r)[1] for r in rows], axis=0)
    norm = plt.Normalize(0.0, max(max(len(r["robot_xy"]) - 1, 1) * float(r["dt"]) for r in rows))
    panel = 3.0
    fig, axes = plt.subplots(nrows, cols, figsize=(panel * cols + 0.8, panel * nrows * size[1] / size[0] + 0.9),
                             squeeze=False, layout="constrained")
    for ax, row in zip(axes.flat, rows, strict=False):
        draw_episode(ax, row, time_base, mark_every_s, legend=False, labels=False, size=size, norm=norm)
        ax.tick_params(labelsize=6)
        ax.title.set_fontsize(8)
    for ax in axes.flat[len(rows):]:
        ax.axis("off")
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=TIME_CMAP), ax=axes.ravel().tolist(),
                 label="time since start (s)", fraction=0.03, pad=0.02)
    fig.legend(handles=legend_handles(any(r["outcome"] == "collision" for r in rows)), loc="outside lower center",
               ncol=3, fontsize=7, frameon=False)
    fig.suptitle(f"{rows[0]['scene']}: first {len(rows)} episodes, {size[0]:.0f} m x {size[1]:.0f} m each "
                 f"(markers every {mark_every_s:g} s)", fontsize=10)
    return _save(fig, out, dpi=100)


def _save(fig, out: Path, dpi: int = 120, rect=None) -> Path:
    """Save tightly cropped (``rect``: also lay the axes out within it, room left for a figure legend)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if rect is not None:
        fig.tight_layout(rect=rect)
    fig.savefig(out, dpi=dpi, bbox_inches="tight", pad_inches=0.05)
    plt.close(fig)
    return out
