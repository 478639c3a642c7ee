"""The web site's figures and recordings (``crowdbench leaderboard --site DIR --site-figures N``): per
entry, ``N`` evenly strided protocol v1 episodes of one scene, evaluated again with the harness's own
policy construction (a learned entry behind its worker process, :class:`~.worker.WorkerPolicy`, as in
the evaluation), drawn as one small trajectory figure (crowdbench/viz/figures.py), animated as one GIF
per episode that the entry's page plays (crowdbench/viz/video.py, one frame per step) and recorded as
one rerun ``.rrd`` per episode (crowdbench/viz/record.py).

Cached in ``DIR/media/<submission>/media.json`` by the fingerprint of the submission's v1 result, the
scene and ``N``: re-running ``--site`` regenerates only the media of changed results. These episodes
are illustrations; every number on the site comes from ``results.json``.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import torch

from crowdbench.leaderboard.sandbox import DEFAULT_LIMITS, Limits

MEDIA_VERSION = 2  # 2: an animated GIF replay per episode
SCENE = "hotel"  # a paper scene with short episodes
MANIFEST = "media.json"


def _stamp(fp: str, scene: str, n: int) -> dict:
    return {"version": MEDIA_VERSION, "fingerprint": fp, "scene": scene, "episodes": n}


def cached(media: Path, fp: str, scene: str, n: int) -> dict | None:
    """The manifest of ``media`` if it was made from this result (fingerprint), scene and ``n``."""
    try:
        manifest = json.loads((media / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    return manifest if manifest.get("stamp") == _stamp(fp, scene, n) else None


def _figure(rows: list[dict], out: Path, title: str, time_base: str) -> None:
    import matplotlib.pyplot as plt

    from crowdbench.viz.figures import draw_episode

    fig, axes = plt.subplots(1, len(rows), figsize=(3.3 * len(rows), 3.3), squeeze=False)
    for ax, row in zip(axes[0], rows, strict=True):
        draw_episode(ax, row, time_base, legend=False, labels=False)
        ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=80, metadata={"Software": None})
    plt.close(fig)


def make_media(media: Path, sub_dir: Path, fp: str, n: int, scene: str = SCENE,
               limits: Limits = DEFAULT_LIMITS) -> dict:
    """Evaluate ``n`` episodes of ``scene`` for the submission at ``sub_dir`` into ``media`` (emptied
    first): ``trajectories.png``, ``<scene>_epNNN.gif`` and ``.rrd`` per episode and the manifest, returned.
    Raises :class:`~.submission.SubmissionError` (or the evaluation's exception) on failure."""
    from crowdbench.envs.protocol import load_episodes
    from crowdbench.leaderboard.harness import build_policy
    from crowdbench.leaderboard.submission import read_submission
    from crowdbench.leaderboard.tracks import TRACKS
    from crowdbench.protocols.engine import select_episodes
    from crowdbench.protocols.replay import evaluate
    from crowdbench.viz.record import SceneRecorder
    from crowdbench.viz.records import load_rows
    from crowdbench.viz.video import episode_video

    shutil.rmtree(media, ignore_errors=True)
    media.mkdir(parents=True)
    sub = read_submission(sub_dir)
    chosen = dict(enumerate(select_episodes(load_episodes(scene), n)))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the harness's jobs
    policy = build_policy(sub, TRACKS["v1"], limits)
    try:
        with tempfile.TemporaryDirectory(prefix="crowdbench-site-") as tmp:
            evaluate(policy, [scene], n, out_dir=Path(tmp), save_episodes=True,
                     sim_overrides={"frame": policy.frame}, meta={"submission": sub.name},
                     recorder_factory=lambda s: SceneRecorder(s, chosen, media, None, policy_name=sub.name))
            rows, _, time_base = load_rows(Path(tmp))
            _figure(rows, media / "trajectories.png", f"{sub.name}: {scene}, protocol v1", time_base)
            for r in rows:  # plays in the page: no viewer, nothing fetched
                episode_video(r, media / f"{scene}_ep{r['episode']:03d}.gif", time_base, size=3.6, dpi=60)
    finally:
        if hasattr(policy, "close"):
            policy.close()
        torch.set_num_threads(threads)
    manifest = {"stamp": _stamp(fp, scene, n), "figure": "trajectories.png",
                "episodes": [{"episode": r["episode"], "outcome": r["outcome"], "nav_time_s": r["nav_time_s"],
                              "steps": len(r["robot_xy"]) - 1, "recording": f"{scene}_ep{r['episode']:03d}.rrd",
                              "replay": f"{scene}_ep{r['episode']:03d}.gif"} for r in rows]}
    (media / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


def entry_media(out: Path, root: Path, name: str, fp: str | None, n: int, log, limits: Limits = DEFAULT_LIMITS,
                scene: str = SCENE) -> dict | None:
    """The manifest of submission ``name``'s media under ``out/media/name`` (cached, else made); None
    when ``n`` is 0, there is no v1 result (``fp``) or making them failed (logged, retried next run)."""
    if n <= 0 or fp is None:
        return None
    media = out / "media" / name
    manifest = cached(media, fp, scene, n)
    if manifest is not None:
        return manifest
    try:
        manifest = make_media(media, root / "submissions" / name, fp, n, scene, limits)
    except Exception as e:  # noqa: BLE001 - a failing figure loses the figure, not the site
        shutil.rmtree(media, ignore_errors=True)
        log(f"site: {name}: no figures ({type(e).__name__}: {' '.join(str(e).split())[:200]})")
        return None
    log(f"site: {name}: figure and {len(manifest['episodes'])} recording(s) of {scene}")
    return manifest
