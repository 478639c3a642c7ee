"""The leaderboard harness: validate submissions, evaluate them on every track, generate the tables.

Modules: ``schema`` (submission.yaml fields, validation, :func:`make_submission`), ``cache``
(fingerprint, the evaluated code closure), ``tracks`` (the tracks, which entries fit them, their
evaluation), ``harness`` (policies via crowdbench.policies, one evaluation job, local / Ray fan-out),
``board`` (the run loop and ``--check``), ``render`` (protocol v1's tables, plot, the generated blocks of
the README and the docs, diffs), ``track_tables`` (``leaderboard/TRACKS.md``).
The command line is ``crowdbench leaderboard`` (crowdbench/cli.py); field reference and rules:
docs/submitting.md.
"""

# Names resolve on first use (PEP 562): a submission's worker imports ``crowdbench.leaderboard.wire`` and
# must not pay for the board, the renderer and every protocol it never uses (about 1.5 s per worker start).
_SOURCES = {
    "board": ["run"],
    "cache": ["EVAL_MODULES", "HARNESS_VERSION", "code_files", "fingerprint"],
    "harness": ["LAUNCHERS", "build_policy"],
    "render": ["BLOCK_END", "BLOCK_START", "BLOCKS", "diff_rows", "render_block", "render_docs_block",
               "render_readme"],
    "schema": ["DEFAULT_ROOT", "PACKAGE_DIR", "REPO_DIR", "Submission", "SubmissionError", "make_submission",
               "read_submission"],
}
_OWNER = {name: module for module, names in _SOURCES.items() for name in names}

__all__ = ["BLOCKS", "BLOCK_END", "BLOCK_START", "DEFAULT_ROOT", "EVAL_MODULES", "HARNESS_VERSION", "LAUNCHERS", "PACKAGE_DIR",
           "REPO_DIR", "Submission", "SubmissionError", "build_policy", "code_files", "diff_rows", "fingerprint",
           "make_submission", "read_submission", "render_block", "render_docs_block", "render_readme", "run"]
assert sorted(__all__) == sorted(_OWNER)


def __getattr__(name: str):
    module = _OWNER.get(name)
    if module is None:
        raise AttributeError(f"module 'crowdbench.leaderboard' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"crowdbench.leaderboard.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
