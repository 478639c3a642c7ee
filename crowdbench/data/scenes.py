"""ETH/UCY scenes resampled onto the simulator's time grid.

The eight vendored files (see ``eth_ucy/SOURCE.md``) are verified by sha256 before use.
A scene is stored *slot-packed*: at every grid step ``k`` the humans present are placed in
slots ``0..n_k-1`` (sorted by pedestrian id), padded to the scene's maximum ``M``. The
simulator then gathers ``[B, M, 2]`` positions with one index op per step instead of
scanning all pedestrians of the recording.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

DATA_DIR = Path(__file__).resolve().parent / "eth_ucy"

# sha256 from SOURCE.md; a mismatch means the vendored copy was edited or truncated.
SHA256 = {
    "eth": "cf8d3fd342a15f409ebc2a1fc76b91a0f06390bd21f1e11410f3859331ab082b",
    "hotel": "9caa771bb9153d6b809dd0916b6f86761b641e6bbb15e766c1de3133fbbb7fcf",
    "students001": "a6d87f278d94136fe39b8be91555487a29ac77259ae403b9dba2d5c18caf7b5b",
    "students003": "e25798b660634330aa89f8bb259425de720e84d0873902726c1d1f4ccff21d6c",
    "uni_examples": "61f432c0ab3070ed0ef150fbeabcd7baf839cab5495a46e6105bd747f0a092a7",
    "zara1": "1147a1962a09abfb86f28c6cddcac862e095a0cf129b3016385b69eacdd09d85",
    "zara2": "8a649d0f8c9ae75c87c4d23a85f892786b0aa30266e996c7be03e69dafff22ff",
    "zara3": "16b3e899932c4baacd07f45013d5b921f90bc5a29eb2b0fe42f4d7c904ac3108",
}
SCENES = tuple(SHA256)

FRAMES_PER_ROW = 10
# Seconds between two 10-frame rows. ETH's sgan file was resampled from 6-frame
# annotations onto multiples of 10 frames, so one row is 10/6 * 0.4 s (SOURCE.md).
TRUE_ROW_PERIOD = {name: 0.4 for name in SCENES} | {"eth": 2.0 / 3.0}
CONVENTIONAL_ROW_PERIOD = 0.4  # what sgan / Trajectron++ / most papers assume for every file
_EPS = 1e-9


def scene_names() -> tuple[str, ...]:
    return SCENES


def check_scene(name: str) -> str:
    key = name.lower()
    if key not in SHA256:
        raise ValueError(f"unknown scene {name!r}; valid scenes: {', '.join(SCENES)}")
    return key


def row_period(name: str, time_base: str = "true") -> float:
    """Seconds between annotation rows: ``true`` (ETH 2/3 s) or ``0.4`` (paper convention)."""
    if time_base == "true":
        return TRUE_ROW_PERIOD[check_scene(name)]
    if str(time_base) == "0.4":
        return CONVENTIONAL_ROW_PERIOD
    raise ValueError(f"unknown time_base {time_base!r}; valid: 'true', '0.4'")


def read_rows(name: str) -> np.ndarray:
    """The raw ``(N, 4)`` rows ``frame, id, x, y`` of a vendored file, sha256-verified."""
    key = check_scene(name)
    path = DATA_DIR / f"{key}.txt"
    if not path.is_file():
        raise FileNotFoundError(f"scene file missing: {path} (reinstall crowdbench)")
    raw = path.read_bytes()
    digest = hashlib.sha256(raw).hexdigest()
    if digest != SHA256[key]:
        raise ValueError(f"scene file corrupted: {path} has sha256 {digest[:12]}..., expected {SHA256[key][:12]}...")
    return np.loadtxt(path, ndmin=2)


@dataclass(frozen=True)
class Scene:
    """A recording resampled to ``dt``; slot tensors are ``[T, M, ...]``."""

    name: str
    dt: float
    row_period: float
    pos: torch.Tensor  # [T, M, 2] position at grid step k
    prev: torch.Tensor  # [T, M, 2] the same human's position at step k-1 (its own position if it spawned at k)
    vel: torch.Tensor  # [T, M, 2] finite difference of the surrounding keyframes
    valid: torch.Tensor  # [T, M] bool
    ped_id: torch.Tensor  # [T, M] long, -1 on padding
    centre: torch.Tensor  # [2] mean of all annotated positions
    # [T] bool or None (every index up to last_start): the grid indices an episode may start at
    # (a scene made of several parts, e.g. :func:`playback_scene`, keeps each episode inside one part)
    starts: torch.Tensor | None = None

    @property
    def n_steps(self) -> int:
        return self.pos.shape[0]

    @property
    def max_humans(self) -> int:
        return self.pos.shape[1]

    @property
    def duration(self) -> float:
        return (self.n_steps - 1) * self.dt

    def last_start(self, time_limit: int) -> int:
        """Latest grid index at which an episode of ``time_limit`` steps still fits in the recording."""
        return self.n_steps - 1 - time_limit

    def count(self) -> torch.Tensor:
        """Humans present at each grid step, ``[T]``."""
        return self.valid.sum(-1)


def interpolate_tracks(rows: np.ndarray, period: float, dt: float):
    """Resample every track onto ``t_k = k * dt``; time 0 is the file's first frame.

    A pedestrian exists on ``[first, last]`` annotation (inclusive). Between keyframes
    ``i`` and ``i+1`` the position is linear and the velocity is ``(P[i+1]-P[i]) / period``;
    at the last keyframe the last segment's velocity is kept.
    Returns ``(T, tracks)`` with ``tracks = {id: (k0, pos [n,2], vel [n,2])}``.
    """
    frame0 = rows[:, 0].min()
    t_row = (rows[:, 0] - frame0) / FRAMES_PER_ROW * period
    n_steps = int(np.floor(t_row.max() / dt + _EPS)) + 1
    grid = np.arange(n_steps) * dt
    tracks = {}
    for pid in np.unique(rows[:, 1]):
        sel = rows[:, 1] == pid
        tau, xy = t_row[sel], rows[sel, 2:4]
        order = np.argsort(tau)
        tau, xy = tau[order], xy[order]
        k0 = int(np.ceil(tau[0] / dt - _EPS))
        k1 = int(np.floor(tau[-1] / dt + _EPS))
        if k1 < k0 or len(tau) < 2:
            continue  # too short to appear on the grid
        t = grid[k0 : k1 + 1]
        seg = np.clip(np.searchsorted(tau, t + _EPS, side="right") - 1, 0, len(tau) - 2)
        step = xy[seg + 1] - xy[seg]
        alpha = ((t - tau[seg]) / (tau[seg + 1] - tau[seg]))[:, None]
        tracks[int(pid)] = (k0, xy[seg] + alpha * step, step / (tau[seg + 1] - tau[seg])[:, None])
    return n_steps, tracks


def pack_slots(n_steps: int, tracks: dict):
    """Slot-pack tracks: at each step the present humans, sorted by id, fill slots 0..n-1."""
    counts = np.zeros(n_steps, dtype=np.int64)
    for k0, p, _ in tracks.values():
        counts[k0 : k0 + len(p)] += 1
    m = max(int(counts.max()), 1)
    pos = np.zeros((n_steps, m, 2))
    prev = np.zeros((n_steps, m, 2))
    vel = np.zeros((n_steps, m, 2))
    ped = -np.ones((n_steps, m), dtype=np.int64)
    fill = np.zeros(n_steps, dtype=np.int64)
    for pid in sorted(tracks):
        k0, p, v = tracks[pid]
        ks = np.arange(k0, k0 + len(p))
        slot = fill[ks]
        fill[ks] += 1
        pos[ks, slot] = p
        vel[ks, slot] = v
        prev[ks, slot] = np.concatenate([p[:1], p[:-1]])
        ped[ks, slot] = pid
    return pos, prev, vel, ped


@lru_cache(maxsize=32)
def load_scene(name: str, dt: float = 0.25, time_base: str = "true") -> Scene:
    """Load, verify and resample a scene. Cached: scenes are immutable."""
    key = check_scene(name)
    rows = read_rows(key)
    period = row_period(key, time_base)
    n_steps, tracks = interpolate_tracks(rows, period, dt)
    pos, prev, vel, ped = pack_slots(n_steps, tracks)
    f32 = lambda a: torch.as_tensor(a, dtype=torch.float32)
    return Scene(
        name=key,
        dt=dt,
        row_period=period,
        pos=f32(pos),
        prev=f32(prev),
        vel=f32(vel),
        valid=torch.as_tensor(ped >= 0),
        ped_id=torch.as_tensor(ped),
        centre=f32(rows[:, 2:4].mean(0)),
    )


def playback_scene(name: str, dt: float, speeds: tuple[float, ...], episode_steps: int,
                   time_base: str = "true") -> Scene:
    """The recording replayed at each playback speed of ``speeds`` (1 = as recorded, 2 = twice as fast),
    the parts one after the other, each followed by ``episode_steps + 1`` empty steps.

    At speed ``f`` grid step ``k`` shows the recording at time ``f * k * dt`` (the tracks resampled at
    ``f * dt``) and every velocity is ``f`` times the recorded one: the same paths walked faster. ``starts``
    admits the indices whose ``episode_steps``-step episode stays inside its part. Why: the training
    scene's pedestrians are slow (students001: median 0.52 m/s, 5% above 1.3 m/s) against those of the
    sparse evaluation scenes (hotel 1.27 and 49%, eth 1.47 and 70%; docs/training.md)."""
    parts = [load_scene(name, float(f) * dt, time_base) for f in speeds]
    m, gap = max(p.max_humans for p in parts), int(episode_steps) + 1

    def stack(get, fill):
        out = []
        for p, f in zip(parts, speeds, strict=True):
            x = get(p, float(f))
            block = torch.full((p.n_steps + gap, m, *x.shape[2:]), fill, dtype=x.dtype)
            block[: p.n_steps, : x.shape[1]] = x
            out.append(block)
        return torch.cat(out)

    starts = torch.cat([torch.arange(p.n_steps + gap) < p.n_steps - episode_steps for p in parts])
    return Scene(name=parts[0].name, dt=dt, row_period=parts[0].row_period,
                 pos=stack(lambda p, f: p.pos, 0.0), prev=stack(lambda p, f: p.prev, 0.0),
                 vel=stack(lambda p, f: p.vel * f, 0.0), valid=stack(lambda p, f: p.valid, False),
                 ped_id=stack(lambda p, f: p.ped_id, -1), centre=parts[0].centre, starts=starts)
