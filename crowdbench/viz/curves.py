"""Training curves (``crowdbench plot RUN [RUN ...] [--out FILE] [--smooth N]``): success / collision
rates (training window and the held-out probe), episode return and losses vs environment frames, read
from a run's TorchRL logs: the ``CSVLogger`` files ``RUN/logs/scalars/<name>.csv`` (``step,value`` rows;
``train.logger=csv`` and ``wandb``) or the ``TensorboardLogger`` event files ``RUN/tensorboard/events.*``
(``train.logger=tensorboard``). Runs whose checkpoint configs differ only in the seed (and output/budget
keys) form one group: its mean is drawn with a min-max band over the seeds. The panels form a grid
(two columns), each with its own legend; several groups share one colour each across panels.

Bad input (a missing run, a run without logs, an unreadable file) raises ``ValueError`` with a one-line
message naming the file; the CLI prints it and exits with code 2.
"""

from __future__ import annotations

import fnmatch
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from crowdbench.outputs import check_writable_file
from crowdbench.viz.figures import _Parser, _save

SCALARS = ("logs", "scalars")
TENSORBOARD = "tensorboard"
# keys that do not change what is trained: runs differing only in these are seeds of one config
NOT_CONFIG = ("seed", "out", "resume", "train.max_minutes", "train.total_frames", "train.checkpoint_every",
              "train.save_buffer", "train.logger", "viz", "eval")


def read_csv_scalars(files: list[Path]) -> dict[str, np.ndarray]:
    out = {}
    for f in files:
        try:
            data = np.loadtxt(f, delimiter=",", ndmin=2)
        except ValueError:
            raise ValueError(f"{f}: not a step,value CSV") from None
        if data.size:
            out[f.stem] = data[np.argsort(data[:, 0], kind="stable")]
    return out


def read_tensorboard(files: list[Path]) -> dict[str, np.ndarray]:
    """The scalars of TensorBoard event files, oldest file first: a step logged again (a resumed run
    repeats the steps after its checkpoint) keeps its latest value."""
    try:
        from tensorboard.backend.event_processing.event_file_loader import LegacyEventFileLoader
        from tensorboard.util import tensor_util
    except ImportError:
        raise ValueError(f"{files[0].parent}: reading TensorBoard logs needs the tensorboard package") from None
    series: dict[str, dict[int, float]] = {}
    for f in files:
        events = 0
        try:
            for ev in LegacyEventFileLoader(str(f)).Load():
                events += 1
                for v in ev.summary.value:
                    x = v.simple_value if v.HasField("simple_value") else tensor_util.make_ndarray(v.tensor).item()
                    series.setdefault(v.tag, {})[int(ev.step)] = float(x)
        except Exception as e:  # noqa: BLE001 - a foreign file: one line naming it
            raise ValueError(f"{f}: not a readable TensorBoard event file ({type(e).__name__})") from None
        if not events and f.stat().st_size:  # the loader skips what it cannot read; a real file has a header
            raise ValueError(f"{f}: not a readable TensorBoard event file (no event in {f.stat().st_size} bytes)")
    return {k: np.array(sorted(d.items()), dtype=float).reshape(-1, 2) for k, d in series.items() if d}


def read_scalars(run: Path) -> dict[str, np.ndarray]:
    """``{name: [n, 2] (frames, value)}`` of a run: its CSV logs if it has them, else its TensorBoard events."""
    run = Path(run)
    if not run.is_dir():
        raise ValueError(f"run directory not found: {run}")
    files = sorted(run.joinpath(*SCALARS).glob("*.csv"))
    if files:
        return read_csv_scalars(files)
    events = sorted(run.joinpath(TENSORBOARD).glob("events.out.tfevents.*"))
    if events:
        return read_tensorboard(events)
    raise ValueError(f"no training log in {run}: expected {run.joinpath(*SCALARS)}/<name>.csv (train.logger=csv "
                     f"or wandb) or {run / TENSORBOARD}/events.out.tfevents.* (train.logger=tensorboard)")


def run_config(run: Path) -> dict | None:
    """The run's config from its checkpoint (``weights_only=True``), or ``None`` without one."""
    ckpt = Path(run) / "checkpoint.pt"
    if not ckpt.is_file():
        return None
    import torch

    try:
        return torch.load(ckpt, map_location="cpu", weights_only=True).get("config")
    except Exception:  # noqa: BLE001 - a broken checkpoint only loses the grouping
        return None


def _flat(d, prefix="") -> dict:
    out = {}
    for k, v in (d or {}).items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def group_runs(runs: list[Path]) -> list[tuple[str, list[Path]]]:
    """Runs grouped by config (seed and output/budget keys ignored), labelled by what differs."""
    groups: dict[str, list[Path]] = {}
    flats: dict[str, dict] = {}
    for run in runs:
        cfg = run_config(run)
        if cfg is None:
            key, flat = f"dir:{run}", {"run": Path(run).name}
        else:
            flat = {k: v for k, v in _flat(cfg).items() if not any(k == n or k.startswith(n + ".") for n in NOT_CONFIG)}
            key = json.dumps(flat, sort_keys=True, default=str)
        groups.setdefault(key, []).append(run)
        flats[key] = flat
    keys = list(groups)
    differ = sorted({k for a in keys for k in flats[a] if any(flats[b].get(k) != flats[a][k] for b in keys)})
    out = []
    for key in keys:
        f = flats[key]
        if "run" in f:
            label = f["run"]
        else:
            label = f"{f.get('algo.name', '?')} + {f.get('encoder.name', '?')}"
            extra = [f"{k}={f.get(k, '-')}" for k in differ if k not in ("algo.name", "encoder.name", "run")]
            label = " ".join([label, *extra])
        n = len(groups[key])
        out.append((label + (f" ({n} seeds)" if n > 1 else ""), groups[key]))
    return out


def smooth(y: np.ndarray, n: int) -> np.ndarray:
    """Trailing moving average over ``n`` logged points (``n <= 1``: unchanged)."""
    if n <= 1 or len(y) < 2:
        return y
    c = np.cumsum(np.insert(y, 0, 0.0))
    k = np.minimum(np.arange(1, len(y) + 1), n)
    return (c[1:] - c[np.arange(1, len(y) + 1) - k]) / k


def band(series: list[np.ndarray], n_smooth: int) -> tuple[np.ndarray, ...]:
    """Mean and min/max of several runs' ``[n, 2]`` series on a common frame grid (their overlap)."""
    series = [np.column_stack((s[:, 0], smooth(s[:, 1], n_smooth))) for s in series]
    if len(series) == 1:
        s = series[0]
        return s[:, 0], s[:, 1], s[:, 1], s[:, 1]
    lo, hi = max(s[0, 0] for s in series), min(s[-1, 0] for s in series)
    x = np.unique(np.concatenate([s[:, 0] for s in series]))
    x = x[(x >= lo) & (x <= hi)]
    ys = np.stack([np.interp(x, s[:, 0], s[:, 1]) for s in series])
    return x, ys.mean(0), ys.min(0), ys.max(0)


PANELS = (
    ("success / collision rate", (("success_rate", "-", "training success"), ("probe_*_success", "o--",
                                                                                "probe success"),
                                  ("collision_rate", ":", "training collision"))),
    ("episode return", (("episode_return", "-", "return"),)),
    ("critic loss", (("loss_critic", "-", "critic"),)),
    ("actor loss", (("loss_actor", "-", "actor"),)),
)


def _panel(ax, title: str, spec, groups, logs, colours, n_smooth: int) -> None:
    """One panel: each group's curves of ``spec``; colours name the groups, line styles the curves."""
    several = len(groups) > 1
    for gi, (label, members) in enumerate(groups):
        for pat, style, name in spec:
            for sname in sorted({n for r in members for n in fnmatch.filter(logs[r], pat)}):
                series = [logs[r][sname] for r in members if sname in logs[r]]
                x, m, lo, hi = band(series, n_smooth if sname.startswith("loss") else 1)
                if several:  # the groups' legend is under the figure; here the curves' styles
                    lab = name if len(spec) > 1 and gi == 0 else None
                else:
                    lab = f"{label}: {name}" if len(spec) > 1 else label
                ax.plot(x, m, style, color=colours[gi], lw=1.3, ms=3, label=lab)
                if len(series) > 1:
                    ax.fill_between(x, lo, hi, color=colours[gi], alpha=0.2, lw=0)
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("environment frames", fontsize=8)
    ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 3))
    ax.tick_params(which="both", labelsize=7)
    ax.grid(alpha=0.3)
    if title.startswith("success"):
        ax.set_ylim(-0.02, 1.02)
    if title == "critic loss" and all(ln.get_ydata().min() > 0 for ln in ax.get_lines()):
        ax.set_yscale("log")  # a diverging critic loss spans orders of magnitude
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)


def plot_runs(runs: list[Path], out: Path, n_smooth: int = 20) -> Path:
    """Curves of one or several runs (see the module docstring) in a grid of two columns; returns the PNG."""
    from matplotlib.lines import Line2D

    from crowdbench.viz.palette import distinct_colours

    logs = {Path(r): read_scalars(Path(r)) for r in runs}
    groups = group_runs(list(logs))
    panels = [(title, spec) for title, spec in PANELS
              if any(fnmatch.filter(lg, pat) for lg in logs.values() for pat, _, _ in spec)]
    if not panels:
        raise ValueError(f"no known scalars in {', '.join(map(str, runs))} (expected success_rate, loss_critic, ...)")
    cols = min(len(panels), 2)
    rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.4 * cols, 3.0 * rows), squeeze=False, layout="constrained")
    colours = distinct_colours(len(groups))
    for ax, (title, spec) in zip(axes.flat, panels, strict=False):
        _panel(ax, title, spec, groups, logs, colours, n_smooth)
    spare = list(axes.flat[len(panels):])
    for ax in spare:
        ax.axis("off")
    if any(len(m) > 1 for _, m in groups):
        fig.suptitle(f"mean over seeds, band = min-max; losses smoothed over {n_smooth} logged points", fontsize=9)
    if len(groups) > 1:  # the groups' colours: in the grid's empty cell, else under the grid
        handles, labels = [Line2D([], [], color=c, lw=2) for c in colours], [label for label, _ in groups]
        if spare:
            spare[0].legend(handles, labels, loc="center", fontsize=8, frameon=False, title="runs", title_fontsize=8)
        else:
            fig.legend(handles, labels, loc="outside lower center", ncol=min(len(groups), 2), fontsize=8, frameon=False)
    return _save(fig, out)


def plot_command(argv: list[str]) -> Path:
    p = _Parser(prog="crowdbench plot", description="Training curves of runs (success, collision, return, losses).")
    p.add_argument("runs", nargs="+", metavar="RUN", help="run directories (RUN/logs/scalars/*.csv or RUN/tensorboard/events.*)")
    p.add_argument("--out", default=None, metavar="FILE.png", help="default: <first RUN>/curves.png")
    p.add_argument("--smooth", type=int, default=20, help="moving average over N logged points (N >= 1)")
    a = p.parse_args(argv)
    if a.smooth < 1:
        p.error(f"--smooth: must be an integer >= 1 (got {a.smooth})")
    out = Path(a.out) if a.out else Path(a.runs[0]) / "curves.png"
    check_writable_file(out)
    return plot_runs([Path(r) for r in a.runs], out, a.smooth)


