"""Colours that never repeat: one per method in the leaderboard plots and per run group in the curves."""

from __future__ import annotations

import colorsys

import matplotlib


def distinct_colours(n: int) -> list[tuple[float, float, float]]:
    """``n`` pairwise different RGB colours: tab10 up to 10, tab20 up to 20, beyond that hues evenly
    spaced around the circle at three alternating lightness/saturation levels (no colour recycled)."""
    if n <= 10:
        return [tuple(c) for c in matplotlib.colormaps["tab10"].colors[:n]]
    if n <= 20:
        return [tuple(c) for c in matplotlib.colormaps["tab20"].colors[:n]]
    levels = ((0.45, 0.75), (0.30, 0.85), (0.62, 0.65))  # (lightness, saturation)
    out = []
    for i in range(n):
        light, sat = levels[i % len(levels)]
        out.append(colorsys.hls_to_rgb(i / n, light, sat))
    return out
