"""The committed CrowdNav-track numbers under an ORCA backend: every entry's results re-evaluated with
``env.orca_backend`` set and compared with leaderboard/results/<entry>/<track>.json (the summaries and
every episode's outcome). Exit status 1 if anything differs.

    python benchmarks/orca_backend_numbers.py --backend numba                     # baselines + one learned entry
    python benchmarks/orca_backend_numbers.py --backend numba --entries all
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CROWDNAV_TRACKS = ("crowdnav-circle5", "crowdnav-circle20", "crowdnav-square5")


def compare(entry: str, track: str, backend: str) -> list[str]:
    from crowdbench.envs.factory import sim_config
    from crowdbench.leaderboard.harness import OUTCOME_CHAR, build_policy
    from crowdbench.leaderboard.submission import read_submission
    from crowdbench.leaderboard.tracks import TRACKS, track_config
    from crowdbench.protocols.crowdnav import evaluate_crowdnav

    committed = json.loads((ROOT / "leaderboard" / "results" / entry / f"{track}.json").read_text())
    t = TRACKS[track]
    # the harness's policy (a learned one in its worker process), one torch thread as the harness runs
    policy = build_policy(read_submission(ROOT / "leaderboard" / "submissions" / entry), t)
    cfg = replace(sim_config(track_config(t)["env"]), frame=policy.frame, orca_backend=backend)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            got = evaluate_crowdnav(policy, cfg, [t.setting], None, out_dir=Path(tmp), save_episodes=True)
            rows = [json.loads(line) for line in (Path(tmp) / "episodes.jsonl").read_text().splitlines()]
    finally:
        if hasattr(policy, "close"):
            policy.close()
    outcomes = "".join(OUTCOME_CHAR[r["outcome"]] for r in rows)  # the harness's string (one setting)
    diffs = [f"scenes differ: {got['scenes']} != {committed['scenes']}"] if got["scenes"] != committed["scenes"] else []
    if outcomes != committed["episode_outcomes"][t.setting]:
        diffs.append("episode outcomes differ")
    return diffs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="numba", choices=("numba", "torch"))
    ap.add_argument("--entries", default="orca,straight,gatedgcn_td3_crowdnav_s0",
                    help="comma-separated entries of leaderboard/results, or 'all'")
    ap.add_argument("--tracks", default=",".join(CROWDNAV_TRACKS))
    args = ap.parse_args(argv)
    from crowdbench.numerics import pin

    pin()  # the numerical path of `crowdbench leaderboard` (before torch is imported)
    import torch

    torch.set_num_threads(1)
    entries = args.entries.split(",")
    if args.entries == "all":
        entries = sorted(p.name for p in (ROOT / "leaderboard" / "results").iterdir() if p.is_dir())
    bad = 0
    for entry in entries:
        for track in args.tracks.split(","):
            if not (ROOT / "leaderboard" / "results" / entry / f"{track}.json").is_file():
                continue
            t0 = time.perf_counter()
            diffs = compare(entry, track, args.backend)
            bad += bool(diffs)
            print(f"{entry:32s} {track:18s} {'identical' if not diffs else '; '.join(diffs)} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
