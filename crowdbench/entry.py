"""The ``crowdbench`` console script: pins evaluation's numerical path before torch is imported."""

from __future__ import annotations

import os
import sys

EVALUATING = ("eval", "leaderboard")  # commands whose numbers are official (crowdbench/numerics.py)


def main() -> int:
    # TorchRL's INFO lines and DeprecationWarnings are for its developers; RL_WARNINGS=1 or
    # RL_LOGGING_LEVEL=INFO in the environment bring them back
    os.environ.setdefault("RL_WARNINGS", "0")
    os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")
    try:  # Ctrl-C while torch, Hydra and the CLI are still importing (seconds): one line, no traceback
        if sys.argv[1:2] and sys.argv[1] in EVALUATING:
            from crowdbench.numerics import pin

            pin()
        from crowdbench.cli import main as cli_main

        return cli_main(sys.argv[1:])
    except KeyboardInterrupt:
        print("crowdbench: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
