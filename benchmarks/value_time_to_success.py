"""Time to result of value-lookahead runs (algo=value): training wall time until CrowdNav's 100 validation
cases first reach a target success, per run, read from each run's ``train_log.jsonl``.

    python benchmarks/value_time_to_success.py runs/value/*_s[0-9] --plot docs/img/value_time_to_success.png

A run validates after the imitation phase (its time: collecting the demonstrations plus the fit) and every
``algo.val_every`` RL episodes (the RL phase's wall time, validations included). The test success is the
run's own evaluation on the 500 test cases (results.json), which the harness reproduces. Wall times are the
machine's at the time: the runs shared it with other jobs, so compare them with the load they ran at.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path


def curve(run: Path) -> list[tuple[float, float]]:
    """``[(minutes, validation success)]``: after imitation, then at each RL validation."""
    rows = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines() if line.strip()]
    il = next(r for r in rows if "il_fit_s" in r)
    il_s = il["il_collect_s"] + il["il_fit_s"]
    out = []
    for r in rows:
        if "val_success" in r:
            out.append(((il_s + r.get("wall_s", 0.0)) / 60, r["val_success"]))
    return out


def first(points: list[tuple[float, float]], target: float) -> float | None:
    return next((t for t, s in points if s >= target - 1e-6), None)  # (logged as float32: 0.95 is 0.9499999)


def label(run: Path) -> tuple[str, int]:
    """``(method, seed)`` from a run directory named ``<method>_<lookahead>[_tag]_s<seed>``."""
    m = re.fullmatch(r"(.+)_s(\d+)", run.name)
    return (m.group(1), int(m.group(2))) if m else (run.name, 0)


def test_success(run: Path) -> float | None:
    try:
        res = json.loads((run / "results.json").read_text())
    except (OSError, ValueError):
        return None
    return next(iter(res["scenes"].values()))["success_rate"]["mean"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--targets", type=float, nargs="+", default=[0.95, 0.99])
    ap.add_argument("--plot", type=Path, default=None)
    args = ap.parse_args()
    runs = sorted((r for r in args.runs if (r / "train_log.jsonl").is_file()), key=label)
    curves = {r: curve(r) for r in runs}
    head = " | ".join(f"to {t:.2f} (min)" for t in args.targets)
    print(f"| run | seed | {head} | validations | test success |")
    print("|---|---|" + "---|" * len(args.targets) + "---|---|")
    for r in runs:
        method, seed = label(r)
        cells = [f"{t:.1f}" if t is not None else "not reached" for t in (first(curves[r], x) for x in args.targets)]
        vals = ", ".join(f"{s:.2f}@{t:.1f}" for t, s in curves[r])
        test = test_success(r)
        print(f"| {method} | {seed} | {' | '.join(cells)} | {vals} | {'—' if test is None else f'{test:.3f}'} |")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        methods = sorted({label(r)[0] for r in runs})
        colours = {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(methods)}
        fig, ax = plt.subplots(figsize=(7, 4))
        for r in runs:
            m, _ = label(r)
            t, s = zip(*curves[r], strict=True)
            ax.plot(t, s, marker="o", color=colours[m], label=m if r == next(x for x in runs if label(x)[0] == m) else None)
        for target in args.targets:
            ax.axhline(target, color="grey", lw=0.8, ls="--")
        ax.set_xlabel("training wall time (min; imitation, then deep V-learning)")
        ax.set_ylabel("success on the 100 validation cases")
        low = min(v for r in runs for _, v in curves[r])
        ax.set_ylim(max(0.0, round(low - 0.1, 1)), 1.02)
        ax.legend(fontsize=8, loc="lower right")
        fig.tight_layout()
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.plot, dpi=120)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
