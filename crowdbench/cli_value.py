"""``algo=value`` runs: train (:func:`crowdbench.algos.value_train.train_value`), then evaluate the greedy
lookahead policy on CrowdNav's test cases through the evaluation loop (the candidates computed on the
harness side). ``crowdbench run env=crowdnav algo=value ...`` lands here; ``python -m crowdbench.cli_value
OVERRIDES`` is the same without the CLI's checks.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def run_value(cfg, out: Path, overrides: list[str], evaluate=None, resume: bool = False) -> dict:
    """Train into ``out`` (``resume``: continue its deep V-learning) and evaluate (``evaluate(policy, cfg, out,
    overrides)``; default: CrowdNav's 500 test cases of ``env.eval_settings``). Results carry ``privileged:
    true`` with ``lookahead=query``."""
    from crowdbench.algos.checkpoint import policy_from_checkpoint
    from crowdbench.algos.curriculum import stages
    from crowdbench.algos.value_train import train_value

    stages(cfg)  # a curriculum over agents is self-play's: refused here in one line, not ignored
    stats = train_value(cfg, out, resume=resume)
    policy = policy_from_checkpoint(out / "checkpoint.pt")
    t0 = time.perf_counter()
    if evaluate is None:
        from crowdbench.app import run_protocol as evaluate
    results = evaluate(policy, cfg, out, overrides)
    stats["eval_s"] = time.perf_counter() - t0
    (out / "train_stats.json").write_text(json.dumps(stats, indent=1, default=float))
    return results


def main(argv: list[str] | None = None) -> int:
    from crowdbench.compose import compose

    overrides = ["env=crowdnav", "algo=value", *(sys.argv[1:] if argv is None else argv)]
    cfg = compose(overrides)
    out = Path(cfg.out or f"outputs/run-value-{cfg.algo.net}-{time.strftime('%Y%m%d-%H%M%S')}")
    res = run_value(cfg, out, overrides)
    for name, m in res["scenes"].items():
        print(name, {k: m[k] for k in m if k in ("success_rate", "collision_rate", "nav_time")})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
