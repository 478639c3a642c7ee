"""The leaderboard harness: validate submissions, evaluate them on every track, generate the tables.

Modules: ``schema`` (submission.yaml fields, validation, :func:`make_submission`), ``cache``
(fingerprint, the evaluated code closure), ``tracks`` (the tracks, which entries fit them, their
evaluation), ``harness`` (policies via crowdbench.policies, one evaluation job, local / Ray fan-out),
``board`` (the run loop and ``--check``), ``render`` (protocol v1's tables, plot, the generated blocks of
the README and the docs, diffs), ``track_tables`` (``leaderboard/TRACKS.md``).
The command line is ``crowdbench leaderboard`` (crowdbench/cli.py); field reference and rules:
docs/submitting.md.
"""

from crowdbench.leaderboard.board import run
from crowdbench.leaderboard.cache import EVAL_MODULES, HARNESS_VERSION, code_files, fingerprint
from crowdbench.leaderboard.harness import LAUNCHERS, build_policy
from crowdbench.leaderboard.render import (
    BLOCK_END,
    BLOCK_START,
    BLOCKS,
    diff_rows,
    render_block,
    render_docs_block,
    render_readme,
)
from crowdbench.leaderboard.submission import (
    DEFAULT_ROOT,
    PACKAGE_DIR,
    REPO_DIR,
    Submission,
    SubmissionError,
    make_submission,
    read_submission,
)

__all__ = ["BLOCKS", "BLOCK_END", "BLOCK_START", "DEFAULT_ROOT", "EVAL_MODULES", "HARNESS_VERSION", "LAUNCHERS", "PACKAGE_DIR",
           "REPO_DIR", "Submission", "SubmissionError", "build_policy", "code_files", "diff_rows", "fingerprint",
           "make_submission", "read_submission", "render_block", "render_docs_block", "render_readme", "run"]
