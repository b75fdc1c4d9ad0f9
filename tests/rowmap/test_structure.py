"""rowmap/structure and the season's registration on it: a row's stems, leaves and floor, moved as another
date's odometry would place them, with leaves turned and missing and no fruit shared."""
import datetime as dt

import numpy as np
import pandas as pd
import pytest

from rowmap import structure as st
from rowmap.season import registration
from rowmap.season.tracks import Config, DateRows, track_season

from test_season import yaw_move


def plant_row(rng: np.random.Generator, leaf_turn_deg: float = 0.0, keep_leaves: float = 1.0) -> np.ndarray:
    """Points [N, 3] (world) of a 2.4 m row seen from the aisle (y = 0): floor strip, stems at irregular x
    (the side facing the aisle), leaves as small tilted patches; leaves optionally turned about their base and
    thinned (another date). Same rng seed, same row."""
    floor = np.stack(np.meshgrid(np.arange(-0.2, 2.4, 0.02), np.arange(0.2, 0.9, 0.02)), -1).reshape(-1, 2)
    pts = [np.column_stack([floor, np.zeros(len(floor))])]
    stems = np.cumsum(rng.uniform(0.2, 0.45, 8)) - 0.1
    for x in stems:
        z = np.arange(0.0, 1.4, 0.01)
        a = np.linspace(-1.2, 1.2, 5)
        pts.append(np.stack([x + 0.01 * np.sin(a)[None].repeat(len(z), 0).ravel(),
                             0.7 - 0.01 * np.cos(a)[None].repeat(len(z), 0).ravel(), np.repeat(z, len(a))], 1))
    u, v = np.meshgrid(np.linspace(0, 0.12, 10), np.linspace(-0.03, 0.03, 5))
    patch = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1)
    for x in stems:
        for z in rng.uniform(0.3, 1.3, 6):
            rot = yaw_move(rng.uniform(0, 360), (0, 0, 0))[:3, :3] @ np.array(
                [[1, 0, 0], [0, np.cos(0.5), -np.sin(0.5)], [0, np.sin(0.5), np.cos(0.5)]])
            turn = yaw_move(rng.normal(0, leaf_turn_deg), (0, 0, 0))[:3, :3]
            keep = rng.random() < keep_leaves
            if keep:
                pts.append((turn @ rot @ patch.T).T + [x, 0.7, z])
    return np.concatenate(pts)


def drifted(world: np.ndarray, move: np.ndarray, drift_per_m: float) -> np.ndarray:
    """World points in another date's row frame: moved rigidly, then x stretched and y bent as odometry drifts."""
    p = registration.apply(np.linalg.inv(move), world)
    return p + drift_per_m * np.stack([p[:, 0], p[:, 0] ** 2, 0 * p[:, 0]], 1)


def test_the_voxel_cloud_averages_each_voxel_and_keeps_its_majority_stuff_class():
    cloud = st.VoxelCloud(voxel_m=0.01, fold_every=3)           # folds between the two adds
    cloud.add(np.array([[0.001, 0.001, 0.001], [0.003, 0.003, 0.003], [0.5, 0.5, 0.5]]), np.array([1, 1, 0]))
    cloud.add(np.array([[0.005, 0.005, 0.005]]), np.array([0]))
    t = cloud.table().sort_values("x_m").reset_index(drop=True)
    assert len(t) == 2 and list(t.n_points) == [3, 1] and list(t.class_id) == [1, 0]
    np.testing.assert_allclose(t.loc[0, ["x_m", "y_m", "z_m"]].astype(float), 0.003, atol=1e-6)


def test_frame_points_keep_stuff_pixels_with_depth_within_the_limit():
    sem = np.array([[0, 1, 2], [255, 1, 4]])
    depth = np.array([[1.0, 2.0, 1.0], [1.0, 0.0, 1.0]], np.float32)
    pts, cls = st.frame_points(depth, sem, np.array([1.0, 1.0, 0.0, 0.0]), np.eye(4), max_depth_m=1.5)
    assert list(cls) == [0] and np.allclose(pts, [[0.5, 0.5, 1.0]])   # fruit, void, too far, no depth: out


def test_the_structure_registers_a_date_that_shares_no_fruit_despite_drift_and_moved_leaves():
    world0 = plant_row(np.random.default_rng(3))
    world1 = plant_row(np.random.default_rng(3), leaf_turn_deg=4.0, keep_leaves=0.8)
    move = yaw_move(1.0, (0.23, -0.04, 0.01))
    fixed = st.Structure.from_points(world0)
    moving = st.Structure.from_points(drifted(world1, move, 0.015))
    reg, share = registration.register_structure(moving, fixed, registration.IDENTITY, max_shift_m=0.6,
                                                 bandwidth_m=0.3)
    probe = np.stack([np.linspace(0.1, 2.0, 20), np.full(20, 0.62), np.linspace(0.4, 1.2, 20)], 1)  # fruits' places
    err = np.linalg.norm(reg(drifted(probe, move, 0.015)) - probe, axis=1)
    rigid = np.linalg.norm(registration.apply(reg.transform, drifted(probe, move, 0.015)) - probe, axis=1)
    assert np.median(err) < 0.004 and err.max() < 0.012, err
    assert np.median(err) < 0.5 * np.median(rigid)                    # the drift is the local offsets' part
    assert share > 0.5


def test_coarse_shift_finds_the_offset_within_max_shift_only():
    pts = plant_row(np.random.default_rng(4))
    shift, overlap = st.coarse_shift(pts - [0.3, 0.02, 0.0], pts, max_shift_m=0.6)
    np.testing.assert_allclose(shift, [0.3, 0.02, 0.0], atol=0.031)
    assert overlap > 0.8
    assert np.hypot(*st.coarse_shift(pts - [0.3, 0.0, 0.0], pts, max_shift_m=0.2)[0][:2]) <= 0.2


def fruit_date(seq: str, day: float, xyz: np.ndarray, world_to_row: np.ndarray, struct: np.ndarray | None) -> DateRows:
    p = registration.apply(world_to_row, xyz)
    f = pd.DataFrame({"fruit_id": np.arange(1, len(p) + 1), "x_m": p[:, 0], "y_m": p[:, 1], "z_m": p[:, 2],
                      "diameter_m": 0.05, "class_name": "fruit_green"})
    cams = registration.apply(world_to_row, np.stack([np.linspace(0, 2.0, 30), np.zeros(30), np.full(30, 0.75)], 1))
    return DateRows(seq, dt.date(2020, 9, 1) + dt.timedelta(days=int(day)), day, f, cams, struct)


@pytest.mark.parametrize("registration_on", ["structure", "fruits"])
def test_track_registration_rests_on_the_structure_when_the_dates_share_no_fruit(registration_on):
    rng = np.random.default_rng(5)
    first = np.stack([np.linspace(0.2, 1.8, 8), np.full(8, 0.62), rng.uniform(0.5, 1.1, 8)], 1)
    later = first[:4] + [0.1, 0.0, 0.1]                                  # new fruits, none where the old ones hung
    move = np.linalg.inv(yaw_move(0.5, (0.3, 0.02, 0.0)))
    d0 = fruit_date("a", 0, first, np.eye(4), plant_row(np.random.default_rng(6)))
    d1 = fruit_date("b", 7, later, move, registration.apply(move, plant_row(np.random.default_rng(6), 3.0, 0.9)))
    season = track_season([d0, d1], Config(registration=registration_on))
    placed = season.transforms[1](d1.fruits[["x_m", "y_m", "z_m"]].to_numpy())
    err = np.median(np.linalg.norm(placed - later, axis=1))
    assert season.registered_on == ["first date", registration_on]
    assert list(season.dates.registered_on) == ["first date", registration_on]
    if registration_on == "structure":
        assert err < 0.005
    else:
        assert err > 0.05                                                 # nothing to agree on: no fruit stayed


def test_a_date_without_structure_falls_back_to_its_fruits():
    rng = np.random.default_rng(7)
    xyz = np.stack([np.linspace(0.2, 1.8, 10), np.full(10, 0.62), rng.uniform(0.5, 1.1, 10)], 1)
    d0 = fruit_date("a", 0, xyz, np.eye(4), plant_row(np.random.default_rng(8)))
    d1 = fruit_date("b", 7, xyz, np.linalg.inv(yaw_move(0, (0.1, 0, 0))), None)
    season = track_season([d0, d1], Config())
    assert season.registered_on[1] == "fruits" and season.tracks.track_id.nunique() == 10


def test_registration_setting_is_checked():
    with pytest.raises(ValueError, match="track.registration"):
        Config(registration="stems")
