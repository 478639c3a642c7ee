"""Scene loading against known rows of the vendored files (hand-computed interpolation)."""

import shutil

import numpy as np
import pytest
import torch

from crowdbench.data import scenes as sc
from crowdbench.data.scenes import SCENES, load_scene, read_rows


def at(scene, k, pid):
    """Position and velocity of pedestrian ``pid`` at grid step ``k`` (None if absent)."""
    hit = (scene.ped_id[k] == pid).nonzero()
    if len(hit) == 0:
        return None
    j = int(hit[0, 0])
    return scene.pos[k, j].tolist(), scene.vel[k, j].tolist(), scene.prev[k, j].tolist()


def test_all_scenes_verify_and_load():
    for name in SCENES:
        s = load_scene(name)
        assert s.n_steps > 100 and s.max_humans >= 1
        assert torch.isfinite(s.pos[s.valid]).all()


def test_students003_first_row_exact():
    # file row 1: "0.0 1.0 9.0499997139 6.03809293275" -> step 0 (t = 0)
    pos, _, prev = at(load_scene("students003"), 0, 1)
    assert pos == pytest.approx([9.0499997139, 6.03809293275], abs=1e-5)
    assert prev == pos  # spawned at step 0: no earlier position


def test_eth_true_time_base_interpolation():
    # eth.txt: frame 780 ped 1 (8.46, 3.59); frame 790 (9.57, 3.79); frame 800 (10.67, 3.99).
    # True row period 2/3 s: t = 0.5 s is 3/4 of the way from row 780 to row 790.
    s = load_scene("eth")
    assert s.row_period == pytest.approx(2 / 3)
    pos, vel, prev = at(s, 2, 1)
    assert pos == pytest.approx([8.46 + 0.75 * 1.11, 3.59 + 0.75 * 0.20], abs=1e-5)
    assert vel == pytest.approx([1.11 / (2 / 3), 0.20 / (2 / 3)], abs=1e-5)
    assert prev == pytest.approx([8.46 + 0.375 * 1.11, 3.59 + 0.375 * 0.20], abs=1e-5)  # t = 0.25 s
    # t = 0.75 s is 1/8 past row 790 (t = 2/3 s), on the next segment with its own velocity
    pos, vel, _ = at(s, 3, 1)
    assert pos == pytest.approx([9.57 + 0.125 * 1.10, 3.79 + 0.125 * 0.20], abs=1e-5)
    assert vel == pytest.approx([1.10 / (2 / 3), 0.20 / (2 / 3)], abs=1e-5)


def test_eth_paper_time_base_option():
    s = load_scene("eth", time_base="0.4")
    # with 0.4 s rows, t = 0.5 s is 1/4 past row 790 (t = 0.4 s)
    pos, vel, _ = at(s, 2, 1)
    assert pos == pytest.approx([9.57 + 0.25 * 1.10, 3.79 + 0.25 * 0.20], abs=1e-5)
    assert vel == pytest.approx([1.10 / 0.4, 0.20 / 0.4], abs=1e-5)
    with pytest.raises(ValueError, match="time_base"):
        load_scene("eth", time_base="0.5")


def test_spawn_and_despawn_at_track_ends():
    # ETH ped 2 first appears at frame 800 = 4/3 s: first grid step is ceil(5.33) = 6 (1.5 s)
    s = load_scene("eth")
    assert at(s, 5, 2) is None and at(s, 6, 2) is not None
    rows = read_rows("eth")
    track = rows[rows[:, 1] == 2]
    t_last = (track[:, 0].max() - rows[:, 0].min()) / 10 * (2 / 3)
    k_last = int(np.floor(t_last / 0.25 + 1e-9))
    assert at(s, k_last, 2) is not None and at(s, k_last + 1, 2) is None
    # the last keyframe is exactly on the grid or before it; the position there is on the last segment
    x_end = track[-1, 2:4] + (k_last * 0.25 - t_last) / (2 / 3) * (track[-1, 2:4] - track[-2, 2:4])
    assert at(s, k_last, 2)[0] == pytest.approx(x_end.tolist(), abs=1e-4)


def test_centre_and_counts_match_source_statistics():
    # SOURCE.md: students001 mean (8.11, 7.04), max 75 per frame; eth mean (5.26, 5.31)
    assert load_scene("students001").centre.tolist() == pytest.approx([8.11, 7.04], abs=0.01)
    assert load_scene("students001").max_humans == 75
    assert load_scene("eth").centre.tolist() == pytest.approx([5.26, 5.31], abs=0.01)


def test_eth_has_empty_stretches():
    assert (load_scene("eth").count() == 0).any()


def test_unknown_scene_lists_valid():
    with pytest.raises(ValueError, match="unknown scene 'mars'.*students003"):
        load_scene("mars")


def test_corrupted_and_missing_files(tmp_path, monkeypatch):
    shutil.copy(sc.DATA_DIR / "hotel.txt", tmp_path / "hotel.txt")
    with open(tmp_path / "hotel.txt", "a") as f:
        f.write("99999\t1.0\t0.0\t0.0\n")
    monkeypatch.setattr(sc, "DATA_DIR", tmp_path)
    with pytest.raises(ValueError, match="corrupted.*hotel.txt"):
        read_rows("hotel")
    with pytest.raises(FileNotFoundError, match="missing.*eth.txt"):
        read_rows("eth")
