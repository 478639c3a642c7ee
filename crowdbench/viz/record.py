"""Rerun recordings (``.rrd``) of evaluation episodes, with the robot's attention (paper Fig. 5).

:func:`make_recorder_factory` returns the ``recorder_factory`` that :func:`crowdbench.protocols.replay.evaluate`
calls once per scene. Its :class:`SceneRecorder` is the rollout's recorder hook:

- ``recorder(sim, td, action)`` before every step ``k``: the state at step ``k`` (humans with
  their ids, robot, goal, sensing radius, the robot's path so far, velocity arrows) and, for
  encoders with gates, the robot's attention: one line per incoming edge of the last layer
  (humans and the goal node) whose width and colour encode the gate value, labelled with it;
- ``recorder.after_step(sim, info)`` after it: the reward of the step, the outcome and the final state;
- ``recorder.close()`` when the batch is done.

Only the selected episodes of the batch are written, each to its own file (headless,
``RecordingStream.save``). Timelines: ``step`` (sequence, episode step) and ``time`` (duration,
``step * dt`` seconds since the episode start). Entity paths (:data:`ENTITIES`)::

    world/robot  world/goal  world/start  world/sensing  world/trajectory
    world/humans  world/humans/trails  world/velocity/robot  world/velocity/humans
    world/attention   (LineStrips2D + AnyValues gate, node, ped_id: the exact gate values)
    scalars/min_clearance  scalars/speed  scalars/reward   events (TextLog)   info (TextDocument)

Attention values are ``encoder.last_gates.values`` (mean over the D channels of eta, Eq. 5) of
the policy call that chose the step's action. Line radius = ``ATTN_WIDTH * gate`` (absolute); colour
= the gate relative to the step's largest one (plasma: yellow = the most attended edge), because the
channel means of a trained model lie close together (0.19-0.26 over 5 edges for the 30-minute TD3 run).
Open a recording with ``rerun FILE.rrd``.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from crowdbench.envs.protocol import load_episodes
from crowdbench.envs.rules import OUTCOMES, RUNNING

ENTITIES = (
    "world/robot", "world/goal", "world/start", "world/sensing", "world/trajectory", "world/humans",
    "world/humans/trails", "world/velocity/robot", "world/velocity/humans", "world/attention",
    "scalars/min_clearance", "scalars/speed", "scalars/reward", "events", "info",
)
ROBOT_COLOUR = (30, 110, 230)
GOAL_COLOUR = (220, 40, 40)
SEEN_COLOUR = (250, 140, 20)
UNSEEN_COLOUR = (160, 160, 160)
ATTN_WIDTH = 0.12  # m: line radius of a gate value of 1


def gate_colours(values: np.ndarray) -> np.ndarray:
    """``[n, 3]`` uint8 colours of gate values in ``[0, 1]`` (matplotlib's plasma map)."""
    cmap = matplotlib.colormaps["plasma"]
    return (cmap(np.clip(values, 0.0, 1.0))[:, :3] * 255).astype(np.uint8)


def find_encoder(policy):
    """The policy network's encoder if it exposes ``last_gates`` (graph encoders), else ``None``."""
    net = getattr(policy, "actor", None)
    if net is None or not hasattr(net, "modules"):
        return None
    for m in net.modules():
        if "last_gates" in dir(type(m)):
            return m
    return None


def recorded_episodes(cfg, scenes: list[str], lists: dict | None = None) -> dict[str, list[int]]:
    """``{scene: [protocol episode ids]}`` to record, checked against the evaluated episodes
    (``lists``, if given, receives each recorded scene's evaluated episode list).

    Raises ``ValueError`` (one line) for an id that is not evaluated or a scene not evaluated.
    """
    from crowdbench.protocols.engine import select_episodes

    v = cfg.viz
    ids = v.episodes
    ids = [ids] if isinstance(ids, int) else list(ids)
    if not ids or not all(isinstance(i, int) and not isinstance(i, bool) for i in ids):
        raise ValueError(f"viz.episodes must be a list of protocol episode ids (integers), got {v.episodes!r}")
    which = scenes if v.scenes is None else ([v.scenes] if isinstance(v.scenes, str) else list(v.scenes))
    out = {}
    for scene in which:
        if scene not in scenes:
            raise ValueError(f"viz.scenes: scene {scene!r} is not evaluated (eval.scenes: {', '.join(scenes)})")
        eps = select_episodes(load_episodes(scene), cfg.eval.episodes)
        if lists is not None:
            lists[scene] = eps
        evaluated = [e["episode"] for e in eps]
        missing = [i for i in ids if i not in evaluated]
        if missing:
            shown = ", ".join(map(str, evaluated[:8])) + (", ..." if len(evaluated) > 8 else "")
            raise ValueError(f"viz.episodes: episode {missing[0]} is not evaluated on {scene} "
                             f"({len(evaluated)} episodes evaluated: {shown})")
        out[scene] = ids
    return out


def make_recorder_factory(policy, cfg, out_dir: Path, scenes: list[str]):
    """``recorder_factory(scene)`` for :func:`crowdbench.protocols.replay.evaluate` (``None`` for unrecorded scenes)."""
    lists: dict[str, list[dict]] = {}
    plan = recorded_episodes(cfg, scenes, lists)
    rec_dir = Path(out_dir) / cfg.viz.dir
    encoder = find_encoder(policy)

    def factory(scene: str):
        if scene not in plan:
            return None
        eps = lists[scene]  # the list evaluate() runs (same protocol file, same selection)
        index = {e["episode"]: b for b, e in enumerate(eps)}
        chosen = {index[i]: eps[index[i]] for i in plan[scene]}
        return SceneRecorder(scene, chosen, rec_dir, encoder, policy_name=policy.name, trail_s=cfg.viz.trail_s)

    return factory


def blueprint():
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin="world", name="scene"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="scalars/min_clearance", name="min clearance (m)"),
                rrb.TimeSeriesView(origin="scalars/speed", name="speed (m/s)"),
                rrb.TimeSeriesView(origin="scalars/reward", name="reward"),
            ),
            column_shares=[3, 1],
        ),
        collapse_panels=True,
    )


class SceneRecorder:
    """Recorder hook for one scene's batch; writes ``<dir>/<scene>_ep<id>.rrd`` per chosen episode."""

    def __init__(self, scene: str, chosen: dict[int, dict], out_dir: Path, encoder=None,
                 policy_name: str = "policy", trail_s: float = 2.0):
        self.scene, self.encoder, self.trail_s = scene, encoder, trail_s
        out_dir.mkdir(parents=True, exist_ok=True)
        self.paths: dict[int, Path] = {}
        self.streams: dict[int, rr.RecordingStream] = {}
        self.episodes = chosen
        self.trails: dict[int, list] = {}
        self.done: set[int] = set()
        for b, ep in chosen.items():
            path = out_dir / f"{scene}_ep{ep['episode']:03d}.rrd"
            rec = rr.RecordingStream("crowdbench", recording_id=f"{scene}-ep{ep['episode']}-{policy_name}")
            rec.save(path, default_blueprint=blueprint())
            rec.log("info", rr.TextDocument(
                f"scene {scene}, protocol episode {ep['episode']}, start time {ep['start_time_s']} s, "
                f"policy {policy_name}", media_type="text/plain"), static=True)
            rec.log("world/start", rr.Points2D([ep["start"]], radii=0.08, colors=ROBOT_COLOUR, labels="start"),
                    static=True)
            rec.log("world/goal", rr.Points2D([ep["goal"]], radii=0.2, colors=GOAL_COLOUR, labels="goal"),
                    static=True)
            self.paths[b], self.streams[b], self.trails[b] = path, rec, []

    # ------------------------------------------------------------------ hook
    def _time(self, rec, k: int, dt: float) -> None:
        rec.set_time("step", sequence=k)
        rec.set_time("time", duration=k * dt)

    def _state(self, rec, sim, b: int, k: int) -> None:
        """Robot, path so far, sensing radius and humans (with ids and short trails) at step ``k``."""
        cfg = sim.cfg
        p = sim.pos[b, 0].tolist()
        self.trails[b].append(p)
        rec.log("world/robot", rr.Points2D([p], radii=cfg.robot_radius, colors=ROBOT_COLOUR, labels="robot"))
        rec.log("world/trajectory", rr.LineStrips2D([self.trails[b]], radii=0.03, colors=ROBOT_COLOUR))
        rec.log("world/sensing", rr.Ellipses2D(centers=[p], half_sizes=[[cfg.sensing_range] * 2],
                                               colors=(120, 120, 220), line_radii=0.02))
        t = int(sim.t[b])
        scene = sim.scene
        valid = scene.valid[t]
        hpos = scene.pos[t][valid].numpy()
        ids = scene.ped_id[t][valid].tolist()
        dist = (scene.pos[t][valid] - sim.pos[b, 0]).norm(dim=-1)
        seen = (dist <= cfg.sensing_range).numpy()
        colours = np.where(seen[:, None], SEEN_COLOUR, UNSEEN_COLOUR).astype(np.uint8)
        rec.log("world/humans", rr.Points2D(hpos, radii=cfg.human_radius, colors=colours,
                                            labels=[str(i) for i in ids]), rr.AnyValues(ped_id=ids))
        t_lo = max(t - round(self.trail_s / cfg.dt), 0)
        # the same slots over the trail window; a slot may have held another pedestrian before
        keep = (scene.valid[t_lo : t + 1] & (scene.ped_id[t_lo : t + 1] == scene.ped_id[t]))[:, valid].numpy()
        win_p = scene.pos[t_lo : t + 1][:, valid].numpy()
        strips = [win_p[keep[:, j], j] for j in range(hpos.shape[0]) if keep[:, j].sum() > 1]
        rec.log("world/humans/trails", rr.LineStrips2D(strips, radii=0.015, colors=UNSEEN_COLOUR))
        hvel = scene.vel[t][valid].numpy()
        rec.log("world/velocity/humans", rr.Arrows2D(origins=hpos, vectors=hvel, colors=colours, radii=0.015))
        # as sim.min_clearance() for this episode only (capped at the sensing range, as the metric)
        clear = float(dist.min()) - sim.radius_sum if len(dist) else cfg.sensing_range
        rec.log("scalars/min_clearance", rr.Scalars(min(clear, cfg.sensing_range)))

    def _attention(self, rec, sim, b: int) -> None:
        gates = self.encoder.last_gates if self.encoder is not None else None
        if gates is None:
            return
        val, nbr, mask = gates.values[b, 0], gates.nbr[b, 0], gates.mask[b, 0]
        val, nbr = val[mask].double().numpy(), nbr[mask].tolist()
        goal_id = sim.M + 1  # node ids: 0 robot, 1..M human slots + 1, M + 1 goal
        hpos = sim.scene.pos[sim.t[b]]
        pids = sim.scene.ped_id[sim.t[b]]
        robot = sim.pos[b, 0].tolist()
        strips, ped = [], []
        for j in nbr:
            src = sim.goal[b, 0] if j == goal_id else hpos[j - 1]
            strips.append([src.tolist(), robot])
            ped.append(-1 if j == goal_id else int(pids[j - 1]))
        rec.log("world/attention",
                rr.LineStrips2D(strips, radii=ATTN_WIDTH * val, colors=gate_colours(val / max(val.max(), 1e-9)),
                                labels=[f"{g:.2f}" for g in val]),
                rr.AnyValues(gate=val, node=nbr, ped_id=ped))

    def __call__(self, sim, td, action) -> None:
        for b, rec in self.streams.items():
            if b in self.done or int(sim.outcome[b, 0]) != RUNNING:
                continue
            k = int(sim.steps[b])
            self._time(rec, k, sim.cfg.dt)
            self._state(rec, sim, b, k)
            self._attention(rec, sim, b)

    def after_step(self, sim, info) -> None:
        """Reward and applied velocity of the step just taken; the final state if the episode ended."""
        for b, rec in self.streams.items():
            if b in self.done or not bool(info.active[b, 0]):
                continue
            k = int(sim.steps[b])  # steps after this one
            self._time(rec, k - 1, sim.cfg.dt)
            start = self.trails[b][-1]
            v = sim.vel[b, 0]
            rec.log("world/velocity/robot", rr.Arrows2D(origins=[start], vectors=[v.tolist()], colors=ROBOT_COLOUR,
                                                        radii=0.03))
            rec.log("scalars/speed", rr.Scalars(float(v.norm())))
            self._time(rec, k, sim.cfg.dt)
            rec.log("scalars/reward", rr.Scalars(float(info.reward[b, 0])))
            outcome = int(info.outcome[b, 0])
            if outcome != RUNNING:
                self._state(rec, sim, b, k)
                if self.encoder is not None:
                    rec.log("world/attention", rr.Clear(recursive=False))
                rec.log("events", rr.TextLog(f"{OUTCOMES[outcome]} after {k} steps ({k * sim.cfg.dt:g} s)"))
                self.done.add(b)
                rec.flush()

    def close(self) -> None:
        for rec in self.streams.values():
            rec.flush()
            rec.disconnect()


def read_recording(path: Path) -> dict[str, list[dict]]:
    """Rows of an ``.rrd`` file per entity path, read back with rerun's own reader (tests, checks):
    ``{entity: [{"step": int | None, "time": timedelta | None, column: value, ...}, ...]}`` sorted by
    step (static rows: no step)."""
    from rerun.chunk import RrdReader

    out: dict[str, list[dict]] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        batch = chunk.to_record_batch()
        cols = [c for c in batch.schema.names if c not in ("log_time", "rerun.controls.RowId")]
        data = {c: batch.column(c).to_pylist() for c in cols}
        for i in range(batch.num_rows):
            out.setdefault(chunk.entity_path.lstrip("/"), []).append({c: data[c][i] for c in cols})
    for rows in out.values():
        rows.sort(key=lambda r: -1 if r.get("step") is None else r["step"])
    return out


__all__ = ["ENTITIES", "SceneRecorder", "find_encoder", "make_recorder_factory", "read_recording",
           "recorded_episodes"]
