"""panoptic_fusion, fruit_count, evaluate and report on a tiny synthetic row with renders fabricated from
ground truth (conftest.py): perfect input must give the ground truth back, perturbed input worse scores."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from scipy.spatial import cKDTree

from nerf.geometry import pose_txyzq
from nerf.surfaces import fruit_sphere, unproject
from pipeline import cli
from pipeline.classes import THING_IDS
from pipeline.images import ImageError, read_label
from pipeline.stage import StageContext
from rowmap.detections import dropped_segments, fruit_segments
from rowmap.geometry import pixel_groups, runs_by_key, sphere_behind, window_alignments, with_sensor_depth
from rowmap.renders import file_name
from rowmap.scoring import reference_pixels
from stages import evaluate, fruit_count, panoptic_fusion, report

from fruitmap_fixture import SEQ, TINY, run_stages


def gt_to_fused(row) -> tuple[dict[int, set[int]], dict[int, set[int]], dict[int, int]]:
    """From the fused PNGs and the ground-truth PNGs of the same frames: gt fruit -> fused ids on its pixels,
    fused id -> gt fruits under it, and gt fruit -> its pixels over the fused frames."""
    pf = pd.read_parquet(row.processed / "panoptic_frames.parquet")
    frames = row.frames.set_index("frame_id")
    g2f: dict[int, set[int]] = {}
    f2g: dict[int, set[int]] = {}
    px: dict[int, int] = {}
    for r in pf.itertuples():
        fused = read_label(row.root / r.instance_path, "fused")
        g_sem = read_label(row.root / frames.loc[r.frame_id, "gt_semantic_path"], "gt")
        g_inst = read_label(row.root / frames.loc[r.frame_id, "gt_instance_path"], "gt")
        thing = np.isin(g_sem, THING_IDS) & (g_inst > 0)
        for g, f in set(zip(g_inst[thing].tolist(), fused[thing].tolist())):
            g2f.setdefault(g, set()).add(f)
            f2g.setdefault(f, set()).add(g)
        ids, n = np.unique(g_inst[thing], return_counts=True)
        for g, k in zip(ids.tolist(), n.tolist()):
            px[g] = px.get(g, 0) + k
    return g2f, f2g, px


def evaluation(row) -> pd.DataFrame:
    return pd.read_parquet(row.processed / "evaluation.parquet")


def metric(ev: pd.DataFrame, scope: str, name: str) -> float:
    v = ev[(ev.scope == scope) & (ev.metric == name)].value
    assert len(v) == 1, (scope, name, sorted(ev.metric.unique()))
    return float(v.iloc[0])


# -- panoptic_fusion -------------------------------------------------------------------------------------

def test_fusion_gives_one_row_level_id_per_ground_truth_fruit(perfect_row):
    g2f, f2g, px = gt_to_fused(perfect_row)
    kept = {g: f - {0} for g, f in g2f.items()}
    # every fruit with enough pixels has exactly one fused id, and no fused id covers two fruits
    assert all(len(f) == 1 for g, f in kept.items() if px[g] >= 4 * 3), {g: f for g, f in kept.items() if len(f) != 1}
    assert all(len(g) == 1 for f, g in f2g.items() if f), {f: g for f, g in f2g.items() if f and len(g) > 1}
    slots = pd.read_parquet(perfect_row.processed / "fruit_slots.parquet")
    multi = slots[slots.fruit_id > 0].groupby("fruit_id").window_id.nunique()
    assert (multi >= 2).sum() >= 3, "fruits seen by several windows must have been fused across them"
    pf = pd.read_parquet(perfect_row.processed / "panoptic_frames.parquet")
    assert pf.frame_id.is_unique and (pf.n_windows >= 1).all() and (pf.n_windows > 1).any()
    # frames shared by two windows come from the window whose centre is nearest
    w = perfect_row.windows
    for r in pf[pf.n_windows > 1].itertuples():
        offs = w[(w.frame_id == r.frame_id) & (w.split == "val")].offset.abs()
        assert abs(r.offset) == offs.min()


def test_fusion_does_not_depend_on_the_windows_slot_numbers(make_row, perfect_row):
    other = make_row(seed=11)
    run_stages(other)
    a = pd.read_parquet(perfect_row.processed / "fruits.parquet")
    b = pd.read_parquet(other.processed / "fruits.parquet")
    assert len(a) == len(b)
    np.testing.assert_allclose(a[["x_m", "y_m", "z_m"]], b[["x_m", "y_m", "z_m"]], atol=1e-9)


def shifted_window_poses(row, window_id: int, t: np.ndarray) -> None:
    """Move every pose of one window by the rigid transform t [4, 4] (as an independent refinement would)."""
    from nerf.geometry import pose_matrix, pose_txyzq

    cols = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    path = row.processed / "window_poses.parquet"
    wp = pd.read_parquet(path)
    sel = wp.window_id == window_id
    wp.loc[sel, cols] = pose_txyzq(t @ pose_matrix(wp.loc[sel, cols].to_numpy(np.float64)))
    wp.to_parquet(path)


def test_windows_placed_apart_by_their_own_refinement_are_aligned_before_fusing(make_row, perfect_row):
    t = np.eye(4)
    yaw = np.radians(3.0)
    t[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    t[:3, 3] = [0.05, 0.04, 0.01]
    truth = pd.read_parquet(perfect_row.processed / "fruits.parquet")
    counts = {}
    for align in (True, False):
        row = make_row(name=f"align_{align}")
        shifted_window_poses(row, 1, t)
        run_stages(row, f"panoptic_fusion.align_windows={str(align).lower()}")
        fruits = pd.read_parquet(row.processed / "fruits.parquet")
        counts[align] = len(fruits)
        if align:
            assert len(fruits) == len(truth)
            np.testing.assert_allclose(fruits[["x_m", "y_m", "z_m"]], truth[["x_m", "y_m", "z_m"]], atol=1e-6)
    assert counts[False] > counts[True]  # unaligned, the fruits both windows saw are counted twice


def test_sphere_centre_does_not_move_with_the_side_a_fruit_is_seen_from():
    rng = np.random.default_rng(2)
    centre, r = np.array([1.0, 0.7, 0.8]), 0.04

    def seen_from(azimuth: float) -> np.ndarray:  # the half of the sphere facing a camera at that azimuth
        d = rng.normal(size=(800, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        view = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
        d = d[d @ view > 0.2]
        return centre + r * d + rng.normal(0, 0.0005, d.shape)

    left, right = seen_from(np.radians(-130)), seen_from(np.radians(-50))
    assert np.linalg.norm(np.median(left, 0) - np.median(right, 0)) > 0.03
    for pts in (left, right):
        assert np.linalg.norm(fruit_sphere(pts, 0.1, min_points=20)[0] - centre) < 0.003


def test_window_alignments_recover_each_windows_transform_from_a_straight_track():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    track = np.tile(np.eye(4), (9, 1, 1))
    track[:, 0, 3] = np.linspace(0, 0.8, 9)                   # collinear camera positions along the row
    track[:, :3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # looking sideways
    frames = {0: range(0, 5), 1: range(3, 8), 2: range(6, 9)}  # windows sharing two frames with the previous
    truth = {0: np.eye(4)}
    rows = []
    for wid, fids in frames.items():
        if wid:
            t = np.eye(4)
            a = rng.normal(size=3)
            t[:3, :3] = Rotation.from_rotvec(0.05 * a / np.linalg.norm(a)).as_matrix()
            t[:3, 3] = 0.03 * rng.normal(size=3)
            truth[wid] = t                                     # window frame -> row frame
        own = np.linalg.inv(truth[wid]) @ track[list(fids)]   # the window's poses in its own frame
        q = pose_txyzq(own)
        rows += [{"window_id": wid, "frame_id": f, **dict(zip(["tx", "ty", "tz", "qx", "qy", "qz", "qw"], q[k]))}
                 for k, f in enumerate(fids)]
    got = window_alignments(pd.DataFrame(rows))
    for wid in frames:
        np.testing.assert_allclose(got[wid], truth[wid], atol=1e-9)


def test_split_slots_become_separate_fruits_and_close_slots_never_merge_within_a_window():
    cfg = panoptic_fusion.Config(max_match_distance_m=0.05)
    c = np.zeros(3)
    fruits = [panoptic_fusion.LocalFruit(0, 1, 0, [(0, 0)], 50, 2, c),
              panoptic_fusion.LocalFruit(0, 2, 0, [(0, 0)], 50, 2, c + [0.01, 0, 0]),
              panoptic_fusion.LocalFruit(1, 5, 0, [(2, 0)], 50, 2, c + [0.005, 0, 0]),
              panoptic_fusion.LocalFruit(2, 9, 0, [(4, 0)], 50, 2, c + [0.3, 0, 0])]
    groups = sorted(sorted(g) for g in panoptic_fusion.associate(fruits, {}, cfg))
    assert groups == [[0, 2], [1], [3]]  # window 1's slot joins the nearer of window 0's two slots
    parts = panoptic_fusion.split_frames({0: c, 1: c + 0.01, 5: c + [0.5, 0, 0], 6: None}, 0.08)
    assert parts == [[0, 1, 6], [5]]
    # a one-frame stray cluster is not a fruit of its own; two frames far away are
    far = c + [0.5, 0, 0]
    assert panoptic_fusion.split_frames({0: c, 1: c + 0.01, 5: far, 6: None}, 0.08, min_frames=2) == [[0, 1, 5, 6]]
    assert panoptic_fusion.split_frames({0: c, 1: c, 5: far, 7: far + 0.01}, 0.08, min_frames=2) == [[0, 1], [5, 7]]


def test_mask_overlaps_count_each_pair_of_codes_of_two_windows_once_in_either_order():
    rng = np.random.default_rng(3)
    m0, m1 = rng.integers(0, 4, (12, 10)).astype(np.int32), rng.integers(0, 3, (12, 10)).astype(np.int32)
    ov = panoptic_fusion.MaskOverlaps({(0, 4): m0, (1, 4): m1, (0, 6): m0})   # frame 6: window 0 only
    assert ov.frames(0, 1) == ov.frames(1, 0) == [4] and ov.frames(0, 2) == []
    joint = ov.joint(0, 1, 4)
    assert {(x, y) for x, y, _ in joint} == {(x, y) for x in range(4) for y in range(3)} - {(0, 0)}
    for x, y, n in joint:
        assert n == np.count_nonzero((m0 == x) & (m1 == y))
    assert sorted(ov.joint(1, 0, 4)) == sorted((y, x, n) for x, y, n in joint)


def test_fusion_uses_mask_overlap_on_shared_frames():
    cfg = panoptic_fusion.Config()
    a = panoptic_fusion.LocalFruit(0, 3, 0, [(4, 0)], 50, 2, np.zeros(3))
    b = panoptic_fusion.LocalFruit(1, 8, 0, [(4, 0)], 50, 2, np.full(3, 0.005))
    m_a, m_b = np.zeros((6, 6), np.int32), np.zeros((6, 6), np.int32)
    m_a[:3, :3], m_b[:3, :3] = panoptic_fusion.code(3, 0), panoptic_fusion.code(8, 0)
    assert np.isfinite(panoptic_fusion.pair_cost(a, b, panoptic_fusion.MaskOverlaps({(0, 4): m_a, (1, 4): m_b}), cfg))
    m_b[:] = 0
    m_b[3:, 3:] = panoptic_fusion.code(8, 0)  # close in 3D but disjoint masks on a frame both rendered
    assert panoptic_fusion.pair_cost(a, b, panoptic_fusion.MaskOverlaps({(0, 4): m_a, (1, 4): m_b}), cfg) == np.inf


def test_a_sliver_with_a_poor_centre_still_joins_the_fruit_whose_mask_holds_it():
    cfg = panoptic_fusion.Config(max_match_distance_m=0.04, min_mask_iou=0.3, strong_mask_overlap=0.8,
                                 strong_match_distance_m=0.08)
    a = panoptic_fusion.LocalFruit(0, 3, 0, [(4, 0)], 50, 2, np.zeros(3))
    far = panoptic_fusion.LocalFruit(1, 8, 0, [(4, 0)], 50, 2, np.array([0.06, 0.0, 0.0]))   # 6 cm: a sliver's centre
    m_a, m_b = np.zeros((6, 6), np.int32), np.zeros((6, 6), np.int32)
    m_a[:3, :3], m_b[:3, :2] = panoptic_fusion.code(3, 0), panoptic_fusion.code(8, 0)  # the other window: smaller
    masks = {(0, 4): m_a, (1, 4): m_b}
    assert np.isfinite(panoptic_fusion.pair_cost(a, far, panoptic_fusion.MaskOverlaps(masks), cfg))
    m_b[:] = 0
    m_b[:3, 2:4] = panoptic_fusion.code(8, 0)  # half outside: the 4 cm gate holds
    assert panoptic_fusion.pair_cost(a, far, panoptic_fusion.MaskOverlaps(masks), cfg) == np.inf
    no_shared_frame = panoptic_fusion.MaskOverlaps({(0, 4): m_a})
    assert panoptic_fusion.pair_cost(a, far, no_shared_frame, cfg) == np.inf
    too_far = panoptic_fusion.LocalFruit(1, 8, 0, [(4, 0)], 50, 2, np.array([0.09, 0.0, 0.0]))
    m_b[:] = 0
    m_b[:3, :3] = panoptic_fusion.code(8, 0)
    assert panoptic_fusion.pair_cost(a, too_far, panoptic_fusion.MaskOverlaps(masks), cfg) == np.inf


def test_runs_by_key_gives_each_labels_pixels_in_image_order():
    labels = np.array([[0, 3, 3], [5, 3, 0], [5, 5, 3]])
    v, u = np.nonzero(labels > 0)
    v, u, key, starts, ends = runs_by_key(v, u, labels[v, u])
    runs = {int(key[s]): list(zip(v[s:e].tolist(), u[s:e].tolist())) for s, e in zip(starts, ends)}
    assert runs == {3: [(0, 1), (0, 2), (1, 1), (2, 2)], 5: [(1, 0), (2, 0), (2, 1)]}
    none = runs_by_key(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert len(none[3]) == len(none[4]) == 0


def test_a_slot_over_two_fruits_in_one_frame_splits_into_groups_that_join_their_own_fruit():
    # one slot's pixels in a 20x40 patch: the larger left part on a fruit 0.5 m away, the rest on one 15 cm
    # behind it (a depth jump), and a 2-pixel speck of boundary pixels on the far background
    v, u = np.mgrid[0:20, 0:40]
    v, u = v.ravel(), u.ravel()
    depth = np.where(u < 25, 0.5, 0.65) + 0.001 * np.sin(v)  # a little noise on each surface
    depth[(v == 0) & (u < 2)] = 3.0
    pts = np.stack([u * 0.001, v * 0.001, depth], 1)
    labels = pixel_groups(v, u, pts, gap_m=0.03, min_size=20, max_groups=256)
    left, right = (u < 25) & ~((v == 0) & (u < 2)), u >= 25
    assert set(labels[left]) == {0} and set(labels[right]) == {1}
    assert set(labels[(v == 0) & (u < 2)]) == {0}                        # under min_size: joins the largest
    assert pixel_groups(v, u, pts, 0.0, 20, 256).max() == 0             # gap 0: one group
    assert pixel_groups(v, u, pts, 0.03, 20, max_groups=1).max() == 0   # only the largest group kept
    apart = u % 20 < 10                                                  # two blobs with an image gap between
    flat = np.stack([u * 0.001, v * 0.001, np.full(len(u), 0.5)], 1)
    assert len(set(pixel_groups(v[apart], u[apart], flat[apart], 0.03, 20, 256))) == 2
    assert pixel_groups(v, u, flat, 0.03, 20, 256).max() == 0            # one connected surface
    # frame 2 painted both fruits with the slot: its group on the fruit behind joins the frames that see
    # that fruit with the same slot, not the slot's main part
    c, far = np.zeros(3), np.array([0.0, 0.0, 0.15])
    centres = {(0, 0): c, (1, 0): c, (2, 0): c, (2, 1): far, (3, 0): far, (4, 0): far}
    assert panoptic_fusion.split_frames(centres, 0.08, min_frames=2) == [[(0, 0), (1, 0), (2, 0)],
                                                                        [(2, 1), (3, 0), (4, 0)]]
    with pytest.raises(ValueError, match="group_gap_m must be >= 0"):
        panoptic_fusion.Config(group_gap_m=-1.0)


def sphere_depth(k: np.ndarray, hw: tuple[int, int], spheres: list[tuple[np.ndarray, float]],
                 background_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(z-depth [H, W], index of the sphere each pixel sees, -1 = background) of spheres in front of a camera
    at the origin looking along +z (identity pose)."""
    h, w = hw
    v, u = np.mgrid[0:h, 0:w]
    d = np.stack([(u + 0.5 - k[2]) / k[0], (v + 0.5 - k[3]) / k[1], np.ones((h, w))], -1)  # rays with z = 1
    depth, who = np.full((h, w), background_m), np.full((h, w), -1)
    for i, (c, r) in enumerate(spheres):
        a, b, cc = (d ** 2).sum(-1), -2 * (d @ c), c @ c - r * r
        disc = b * b - 4 * a * cc
        t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        nearer = t < depth
        depth, who = np.where(nearer, t, depth), np.where(nearer, i, who)
    return depth, who


def test_fruit_pixels_on_another_fruits_surface_go_to_that_fruit():
    k = np.array([100.0, 100.0, 40.0, 30.0])
    a, b = (np.array([-0.05, 0.0, 0.5]), 0.03), (np.array([0.05, 0.0, 0.55]), 0.035)
    depth, who = sphere_depth(k, (60, 80), [a, b], background_m=2.0)
    truth = np.where(who == 0, 1, np.where(who == 1, 2, 0)).astype(np.uint16)
    inst = truth.copy()
    stolen = (who == 1) & (np.arange(80)[None] < 48)        # fruit 1's slot painted a piece of fruit 2
    inst[stolen] = 1
    halo = (who == -1) & (np.abs(np.arange(80)[None] - 30) < 9) & (np.abs(np.arange(60)[:, None] - 30) < 3)
    inst[halo] = 1                                           # boundary pixels whose depth is the background
    assert stolen.sum() > 20 and halo.sum() > 0
    # fruits 3 (off to the side) and 4 (behind the camera) are out of view: they take and give nothing
    spheres = {1: a, 2: b, 3: (np.array([2.0, 0.0, 0.5]), 0.03), 4: (np.array([0.0, 0.0, -0.5]), 0.03)}
    moved = panoptic_fusion.relabel_by_surface(inst, depth, k, np.eye(4), spheres, margin_m=0.01)
    assert moved == stolen.sum()
    assert (inst[who >= 0] == truth[who >= 0]).all() and (inst[halo] == 1).all()
    # a fruit without a sphere gives the pixels on another's sphere to it and keeps those on no sphere
    inst[stolen] = 1
    own = inst == 1
    assert panoptic_fusion.relabel_by_surface(inst, depth, k, np.eye(4), {2: b, 3: (np.ones(3), 0.03)}, 0.01) \
        == stolen.sum()
    assert (inst[stolen] == 2).all() and (inst[own & ~stolen] == 1).all()
    # with no sphere in view nothing moves
    inst[stolen] = 1
    assert panoptic_fusion.relabel_by_surface(inst, depth, k, np.eye(4), {3: (np.ones(3), 0.03)}, 0.01) == 0
    # pixels of an out-of-view fruit's id lie on no sphere of theirs: they go to the sphere they lie on
    inst[stolen] = 3
    assert panoptic_fusion.relabel_by_surface(inst, depth, k, np.eye(4), spheres, 0.01) == stolen.sum()
    assert (inst[stolen] == 2).all()
    inst[stolen] = 1
    assert panoptic_fusion.relabel_by_surface(inst, depth, k, np.eye(4), spheres, 0.0) == 0
    with pytest.raises(ValueError, match="track_margin_m"):
        panoptic_fusion.Config(track_margin_m=-0.01)


def test_a_fruit_seen_past_the_outline_of_one_in_front_is_not_given_to_the_front_fruit():
    k = np.array([200.0, 200.0, 80.0, 60.0])
    front, back = (np.array([0.0, 0.0, 0.5]), 0.035), (np.array([0.04, 0.0, 0.54]), 0.03)
    depth, who = sphere_depth(k, (120, 160), [front, back], background_m=2.0)
    v, u = np.nonzero(who == 1)
    points = unproject(depth, k, np.eye(4), v, u)
    near = np.linalg.norm(points - front[0], axis=1) <= front[1] + 0.01    # within the front sphere's reach
    assert near.sum() > 20 and (panoptic_fusion.beyond_centre(points[near], np.zeros(3), front[0]) > 0.01).all()
    truth = np.where(who == 0, 1, np.where(who == 1, 2, 0)).astype(np.uint16)
    # the fruit behind has no sphere (too few points): its pixels past the front fruit's outline stay its own
    inst = truth.copy()
    assert panoptic_fusion.relabel_by_surface(inst, depth, k, np.eye(4), {1: front}, 0.01) == 0
    assert (inst == truth).all()
    # the front fruit's own surface still goes to it from the id the back fruit's slot painted on it
    painted = (who == 0) & (np.arange(160)[None] > 80)
    inst[painted] = 2
    assert panoptic_fusion.relabel_by_surface(inst, depth, k, np.eye(4), {1: front}, 0.01) == painted.sum() > 20
    assert (inst == truth).all()


def test_fruit_pixels_far_off_their_fruits_sphere_are_cleared_unless_the_detector_shows_the_fruit_there():
    k = np.array([100.0, 100.0, 40.0, 30.0])
    a, b = (np.array([-0.05, 0.0, 0.5]), 0.03), (np.array([0.06, 0.0, 0.55]), 0.03)
    depth, who = sphere_depth(k, (60, 80), [a, b], background_m=2.0)
    truth = np.where(who == 0, 1, np.where(who == 1, 2, 0)).astype(np.uint16)
    rows, cols = np.mgrid[0:60, 0:80]
    # fruit 1's silhouette painted 3 px too wide: the sensor sees the background there
    halo = (who == -1) & (cv2.dilate((who == 0).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0)
    piece = (who == 1) & (cols < 52)                 # a piece of fruit 2 painted with fruit 1's id
    assert halo.sum() > 30 and piece.sum() > 20
    inst = truth.copy()
    inst[halo | piece] = 1
    spheres = {1: a, 2: b}
    cleared = panoptic_fusion.clear_off_sphere(inst, None, depth, k, np.eye(4), spheres, 0.01, 1.25)
    assert cleared == halo.sum() + piece.sum()
    assert (inst[halo | piece] == 0).all() and (inst[who == 0] == 1).all()
    assert (inst[(who == 1) & ~piece] == 2).all()
    # a detector segment lying mostly on fruit 1 keeps the pixels it covers where their points do not lie behind
    # the sphere (here the sensor measures something in front of its centre: 5 cm nearer); one lying mostly on
    # fruit 2 does not
    inst = truth.copy()
    inst[halo] = 1
    kept, lost = halo & (rows < 30), halo & (rows >= 36)
    depth = np.where(kept, 0.45, depth)
    segments = np.zeros(inst.shape, np.int32)
    segments[(who == 0) | kept] = 3
    segments[(who == 1) | lost] = 4
    assert kept.sum() > 10 and 0 < lost.sum() < (who == 1).sum()
    alone = inst.copy()
    assert panoptic_fusion.clear_off_sphere(alone, None, depth, k, np.eye(4), spheres, 0.01, 1.25) == halo.sum()
    cleared = panoptic_fusion.clear_off_sphere(inst, segments, depth, k, np.eye(4), spheres, 0.01, 1.25)
    assert cleared == halo.sum() - kept.sum()
    assert (inst[kept] == 1).all() and (inst[halo & ~kept] == 0).all() and (inst[who >= 0] == truth[who >= 0]).all()
    # a fruit's own pixels lie on its sphere, also on one 2 cm wider with its centre 1 cm deeper (a sphere fitted
    # to an elongated fruit), at a factor of 1
    inst = truth.copy()
    wide = {1: (a[0] + np.array([0.0, 0.0, 0.01]), a[1] + 0.02), 2: b}
    assert panoptic_fusion.clear_off_sphere(inst, None, depth, k, np.eye(4), wide, 0.01, 1.0) == 0
    inst[halo] = 1
    # fruits without a sphere keep their pixels; 0 = off
    assert panoptic_fusion.clear_off_sphere(inst, None, depth, k, np.eye(4), {2: b}, 0.01, 1.25) == 0
    assert panoptic_fusion.clear_off_sphere(inst, None, depth, k, np.eye(4), spheres, 0.01, 0.0) == 0
    assert (inst == np.where(halo, 1, truth)).all()
    for bad in (0.5, -1.0):
        with pytest.raises(ValueError, match="off_sphere_factor"):
            panoptic_fusion.Config(off_sphere_factor=bad)


def test_a_detector_mask_reaching_onto_a_fruit_behind_keeps_no_pixels_there_unless_it_lies_behind_as_a_whole():
    k = np.array([100.0, 100.0, 40.0, 30.0])
    front, back = (np.array([0.0, 0.0, 0.5]), 0.03), (np.array([0.05, 0.0, 0.62]), 0.035)
    depth, who = sphere_depth(k, (60, 80), [front, back], background_m=2.0)
    spheres = {1: front, 2: back}
    # the render paints the visible part of the fruit behind with the front fruit's id
    hidden = who == 1
    assert hidden.sum() > 40
    z = depth[hidden]
    v, u = np.nonzero(hidden)
    p = np.stack([(u + 0.5 - k[2]) / k[0] * z, (v + 0.5 - k[3]) / k[1] * z, z], 1)
    past = panoptic_fusion.beyond_centre(p, np.zeros(3), front[0])
    assert (past > front[1] + 0.01).all()                 # all of it lies behind the front fruit's sphere
    painted = np.where(who >= 0, 1, 0).astype(np.uint16)
    # one detector mask over the front fruit that reaches onto the fruit behind: those pixels are cleared
    inst = painted.copy()
    segments = np.where(who >= 0, 5, 0).astype(np.int32)
    assert (who == 0).sum() > hidden.sum()                # the mask lies mostly on the front fruit
    cleared = panoptic_fusion.clear_off_sphere(inst, segments, depth, k, np.eye(4), spheres, 0.01, 1.25)
    assert cleared == hidden.sum() and (inst[hidden] == 0).all() and (inst[who == 0] == 1).all()
    # a mask of the fruit behind alone lies behind the front fruit's sphere as a whole: another fruit under
    # this id, which keeps its pixels where the detector split can take them (at least its min_px)
    inst = painted.copy()
    segments = np.where(who == 0, 5, np.where(hidden, 6, 0)).astype(np.int32)
    n = int(hidden.sum())
    assert panoptic_fusion.clear_off_sphere(inst, segments, depth, k, np.eye(4), spheres, 0.01, 1.25, n) == 0
    assert (inst == painted).all()
    for too_few in (n + 1, 0):        # fewer pixels than the split takes; no split
        assert panoptic_fusion.clear_off_sphere(inst, segments, depth, k, np.eye(4), spheres, 0.01, 1.25,
                                                too_few) == n
        assert (inst[hidden] == 0).all() and (inst[who == 0] == 1).all()
        inst = painted.copy()
    # beside the sphere but not behind it (a halo in the sphere's depth range), the mask keeps its pixels
    rows, cols = np.mgrid[0:60, 0:80]
    beside = (who == -1) & (np.abs(rows - 30) < 2) & (cols >= 25) & (cols < 29)
    flat = np.where(beside, 0.5, depth)
    inst = painted.copy()
    inst[beside] = 1
    segments = np.where((who == 0) | beside, 5, 0).astype(np.int32)
    assert beside.sum() > 4
    cleared = panoptic_fusion.clear_off_sphere(inst, segments, flat, k, np.eye(4), spheres, 0.01, 1.25, 50)
    assert (inst[beside] == 1).all() and cleared == hidden.sum()


def test_a_fruit_whose_render_lies_off_the_sensors_surface_is_judged_where_the_sensor_sees_it(tmp_path):
    # per fused fruit, the medians over its views of (rendered - sensor) depth and of the offset from the
    # rendered to the measured point; views without a sensor depth are skipped
    view = lambda gap, dz: panoptic_fusion.SlotView(10, np.zeros(3), np.zeros((0, 3)), gap,
                                                    None if dz is None else np.array([0.0, 0.0, dz]))
    slot_views = {(0, 1): {(0, 0): view(-0.06, 0.06), (2, 0): view(-0.05, 0.05), (4, 0): view(np.nan, None)},
                  (1, 7): {(4, 0): view(-0.01, 0.01)}, (0, 2): {(0, 0): view(np.nan, None)}}
    local = [panoptic_fusion.LocalFruit(0, 1, 0, [(0, 0), (2, 0), (4, 0)], 30, 2, np.zeros(3), fruit_id=1),
             panoptic_fusion.LocalFruit(1, 7, 0, [(4, 0)], 10, 2, np.zeros(3), fruit_id=1),
             panoptic_fusion.LocalFruit(0, 2, 0, [(0, 0)], 10, 2, np.zeros(3), fruit_id=2)]
    gaps = panoptic_fusion.fruit_render_gaps([[0, 1], [2]], local, slot_views)
    assert set(gaps) == {1} and gaps[1][0] == pytest.approx(-0.05) and np.allclose(gaps[1][1], [0, 0, 0.05])
    # the clearing tolerates (1.25 - 1) x 4 cm + 1 cm = 2 cm beyond a 4 cm sphere
    cfg = panoptic_fusion.Config(detector_fill=False, border_band_px=4)
    ball = (np.zeros(3), 0.04)
    shift = np.array([0.0, 0.0, 0.1])
    gaps = {1: (-0.05, shift), 2: (0.015, shift), 4: (0.3, shift)}
    off = panoptic_fusion.render_off_sensor({1: ball, 2: ball, 3: ball}, gaps, cfg)
    assert list(off) == [1] and (off[1] == shift).all()
    assert panoptic_fusion.render_off_sensor({1: ball}, gaps, panoptic_fusion.Config(off_sphere_factor=0)) == {}
    # fruit 1, cut off by the image's left edge, is rendered 10 cm in front of where the sensor sees it: all its
    # pixels lie off its sphere, and its sliver in the edge band, painted as leaf, off its seen surface
    k = np.array([100.0, 100.0, 40.0, 30.0])
    a, b = (np.array([-0.2, 0.0, 0.5]), 0.03), (np.array([0.06, 0.0, 0.55]), 0.03)
    depth, who = sphere_depth(k, (60, 80), [a, b], background_m=2.0)
    cols = np.arange(80)[None]
    sliver, rest = (who == 0) & (cols < 4), (who == 0) & (cols >= 4)
    halo = (who == -1) & (cv2.dilate((who == 1).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0)
    assert sliver.sum() > 10 and rest.sum() > 10
    truth = np.where(who == 0, 1, np.where(who == 1, 2, 0)).astype(np.uint16)
    rendered = {1: (a[0] - shift, a[1]), 2: b}
    clouds = panoptic_fusion.surface_clouds({f: front_cap(s) for f, s in rendered.items()}, rendered, 0.002)
    ctx = StageContext(stage="panoptic_fusion", seq=SEQ, data_root=tmp_path, show_progress=False)
    for off_sensor in ({}, {1: shift}):
        inst = truth.copy()
        inst[sliver] = 0
        inst[halo] = 2
        seen = panoptic_fusion.moved_surfaces(clouds, off_sensor)
        panoptic_fusion.surface_rules(inst, None, depth, k, np.eye(4), rendered, seen, off_sensor, cfg, ctx)
        # judged against the render's sphere, its pixels are cleared; judged where the sensor sees it, it keeps
        # them and takes back its sliver from its seen surface moved by the offset
        assert (inst[who == 0] == (1 if off_sensor else 0)).all()
        assert (inst[halo] == 0).all() and (inst[who == 1] == 2).all()


def test_a_fruit_takes_the_pixels_of_its_detector_segment_that_lie_on_its_sphere():
    k = np.array([100.0, 100.0, 40.0, 30.0])
    a, b = (np.array([-0.05, 0.0, 0.5]), 0.03), (np.array([0.05, 0.0, 0.55]), 0.035)
    depth, who = sphere_depth(k, (60, 80), [a, b], background_m=2.0)   # fruit 1: columns 24-35, fruit 2: 43-55
    truth = np.where(who == 0, 1, np.where(who == 1, 2, 0)).astype(np.uint16)
    spheres = {1: a, 2: b}
    cols = np.arange(80)[None]
    left = (who == 0) & (cols < 28)                  # the render painted these pixels of fruit 1 as leaf
    right = (who == 1) & (cols > 52)                 # and these of fruit 2
    spill = (who == -1) & (cols < 24) & (cols > 18) & (np.abs(np.arange(60)[:, None] - 30) < 3)
    assert left.sum() > 10 and right.sum() > 10 and spill.sum() > 0
    segments = np.where(who == 0, 5, np.where(who == 1, 6, 0))
    segments[spill] = 5                              # the detector's boundary spills onto the background
    inst = truth.copy()
    inst[left | right] = 0
    before = inst.copy()
    assert panoptic_fusion.fill_from_detector(inst, segments, depth, k, np.eye(4), spheres, 0.01) \
        == left.sum() + right.sum()
    assert (inst == truth).all()                     # the spilled background pixels lie on no sphere
    # a leaf 1.5 cm behind fruit 1's outline: its points lie within the margin of the sphere, but behind the
    # sphere's centre along their rays (the fruit's seen surface faces the camera)
    v, u = np.mgrid[0:60, 0:80]
    ray = np.stack([(u + 0.5 - k[2]) / k[0], (v + 0.5 - k[3]) / k[1], np.ones((60, 80))], -1)
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    along = ray @ a[0]
    beside = np.linalg.norm(along[..., None] * ray - a[0], axis=-1)        # the ray's closest approach
    leaf = (who == -1) & (beside < a[1] + 0.003)
    assert leaf.sum() > 5
    leaf_depth = np.where(leaf, (along + 0.015) * ray[..., 2], depth)       # z-depth 1.5 cm past that point
    assert (np.hypot(beside[leaf], 0.015) < a[1] + 0.01).all()             # within the margin of the sphere
    segments[leaf] = 5
    assert panoptic_fusion.fill_from_detector(inst, segments, leaf_depth, k, np.eye(4), spheres, 0.01) == 0
    segments[leaf] = 0
    # one segment over both fruits belongs to the fruit it covers most (fruit 2): it takes its own pixels
    # back but none of fruit 1's, which lie on fruit 1's sphere; fruit 1 takes nothing from it
    inst = before.copy()
    one = np.where(who >= 0, 7, 0)
    assert (inst[who == 1] == 2).sum() > (inst[who == 0] == 1).sum()
    assert panoptic_fusion.fill_from_detector(inst, one, depth, k, np.eye(4), spheres, 0.01) == right.sum()
    assert (inst[right] == 2).all() and (inst[left] == 0).all()
    # no fill without a margin, and none for a fruit without a sphere
    inst = before.copy()
    assert panoptic_fusion.fill_from_detector(inst, segments, depth, k, np.eye(4), spheres, 0.0) == 0
    assert panoptic_fusion.fill_from_detector(inst, segments, depth, k, np.eye(4), {2: b}, 0.01) == right.sum()
    assert (inst[left] == 0).all()


def masks_of(shape: tuple[int, int], painted: dict[tuple[int, int], list[tuple[int, slice]]]) -> dict:
    """{(window, frame): slot-code image} with each listed (slot, column slice) painted over all rows."""
    out = {}
    for key, slots in painted.items():
        m = np.zeros(shape, np.int32)
        for slot, cols in slots:
            m[:, cols] = panoptic_fusion.code(slot, 0)
        out[key] = m
    return out


def test_a_window_that_paints_a_fruit_with_two_slots_in_turn_gives_it_one_id():
    cfg = panoptic_fusion.Config()
    lf = panoptic_fusion.LocalFruit
    c, x3 = np.zeros(3), np.array([0.03, 0.0, 0.0])
    a = lf(0, 1, 0, [(0, 0), (2, 0)], 50, 2, c)                 # window 0
    b1 = lf(1, 5, 0, [(2, 0), (4, 0)], 50, 2, c)                # window 1, then it loses the fruit ...
    b2 = lf(1, 6, 0, [(8, 0), (10, 0)], 50, 2, x3)              # ... and paints it with another slot
    w2 = lf(2, 9, 0, [(8, 0), (10, 0), (12, 0)], 50, 2, x3)     # window 2
    masks = masks_of((4, 8), {(0, 2): [(1, slice(0, 4))], (1, 2): [(5, slice(0, 4))],
                              (1, 8): [(6, slice(2, 6))], (2, 8): [(9, slice(2, 6))],
                              (1, 10): [(6, slice(2, 6))], (2, 10): [(9, slice(2, 6))]})
    # window 1 shows it on slot 6 where 2 sees it
    assert panoptic_fusion.pair_cost(b1, w2, panoptic_fusion.MaskOverlaps(masks), cfg) == np.inf
    groups = sorted(sorted(g) for g in panoptic_fusion.associate([a, b1, b2, w2], masks, cfg))
    assert groups == [[0, 1, 2, 3]]
    # the two slots of window 1 in one frame are two fruits, and so are two slots of one window far apart
    for b2_other in (lf(1, 6, 0, [(4, 0), (8, 0), (10, 0)], 50, 2, x3),
                     lf(1, 6, 0, [(8, 0), (10, 0)], 50, 2, np.array([0.05, 0.0, 0.0]))):
        w2_near = lf(2, 9, 0, [(8, 0), (10, 0), (12, 0)], 50, 2, b2_other.centre)
        groups = sorted(sorted(g) for g in panoptic_fusion.associate([a, b1, b2_other, w2_near], masks, cfg))
        assert groups == [[0, 1], [2, 3]]


def test_fruits_whose_masks_disagree_on_a_shared_frame_never_join_one_id_through_a_third_window():
    cfg = panoptic_fusion.Config()
    lf = panoptic_fusion.LocalFruit
    c = np.zeros(3)
    main = lf(1, 2, 0, [(2, 0), (4, 0), (6, 0)], 900, 2, np.array([0.02, 0.0, 0.0]))  # window 1: the fruit
    piece = lf(1, 3, 0, [(4, 0), (6, 0)], 60, 2, c + 0.004)                            # ... and a stray piece
    w2 = lf(2, 7, 0, [(4, 0), (6, 0), (8, 0)], 900, 2, c)
    w3 = lf(3, 8, 0, [(10, 0), (12, 0)], 900, 2, c)      # shares no frame with window 1
    painted = [(2, slice(0, 4)), (3, slice(6, 8))]
    masks = masks_of((4, 8), {(1, 4): painted, (1, 6): painted,
                              (2, 4): [(7, slice(0, 3))], (2, 6): [(7, slice(0, 3))]})
    overlaps = panoptic_fusion.MaskOverlaps(masks)
    assert panoptic_fusion.pair_cost(piece, w3, overlaps, cfg) < panoptic_fusion.pair_cost(main, w2, overlaps, cfg)
    groups = sorted(sorted(g) for g in panoptic_fusion.associate([main, piece, w2, w3], masks, cfg))
    assert groups == [[0, 2, 3], [1]]   # the piece's mask misses window 2's fruit, so it stays apart


def test_a_piece_a_window_painted_beside_a_fruits_slot_joins_that_fruit_where_the_other_window_holds_it():
    cfg = panoptic_fusion.Config()
    lf = panoptic_fusion.LocalFruit
    main = lf(1, 2, 0, [(4, 0), (6, 0)], 400, 2, np.zeros(3))
    piece = lf(1, 3, 0, [(4, 0), (6, 0)], 100, 2, np.array([0.01, 0.0, 0.0]))   # same frames: a second slot
    other = lf(2, 7, 0, [(4, 0), (6, 0), (8, 0)], 700, 2, np.array([0.005, 0.0, 0.0]))
    for reach, joins in ((7, True), (4, False)):   # window 2's mask of the fruit covers the piece, or not
        masks = masks_of((4, 8), {(1, 4): [(2, slice(0, 4)), (3, slice(4, 6))],
                                  (1, 6): [(2, slice(0, 4)), (3, slice(4, 6))],
                                  (2, 4): [(7, slice(0, reach))], (2, 6): [(7, slice(0, reach))]})
        groups = sorted(sorted(g) for g in panoptic_fusion.associate([main, piece, other], masks, cfg))
        assert groups == ([[0, 1, 2]] if joins else [[0, 2], [1]])
    far = lf(1, 3, 0, [(4, 0), (6, 0)], 100, 2, np.array([0.06, 0.0, 0.0]))   # beyond max_match_distance_m
    masks = masks_of((4, 8), {(1, 4): [(2, slice(0, 4)), (3, slice(4, 6))], (2, 4): [(7, slice(0, 7))]})
    groups = sorted(sorted(g) for g in panoptic_fusion.associate([main, far, other], masks, cfg))
    assert groups == [[0, 2], [1]]


def test_a_sphere_of_the_fruits_size_puts_the_centre_behind_a_shallow_cap_seen_from_either_side():
    rng = np.random.default_rng(4)
    centre, r = np.array([1.0, 0.7, 0.8]), 0.04
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for azimuth in (-120, -60):
        view = np.array([np.cos(np.radians(azimuth)), np.sin(np.radians(azimuth)), 0.0])
        cap = centre + r * d[d @ view > 0.8] + rng.normal(0, 0.002, (int(np.sum(d @ view > 0.8)), 3))
        eye = centre + 0.6 * view
        assert np.linalg.norm(np.median(cap, 0) - centre) > 0.03          # the median sits on the seen side
        got = sphere_behind(cap, eye, 0.038)
        assert got is not None and np.linalg.norm(got - centre) < 0.006
        assert sphere_behind(cap, eye, 0.0) is None and sphere_behind(cap[:3], eye, 0.04) is None


def front_cap(ball: tuple[np.ndarray, float], n: int = 6000, seed: int = 0) -> np.ndarray:
    """Points on the part of a sphere that a camera at the origin sees: a fruit's seen surface."""
    c, r = ball
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return c + r * d[d @ c < -r]


def two_seen_fruits() -> tuple:
    """Two fruits side by side 50 cm in front of a 80x60 camera: k, balls a and b, the sensor depth, which
    fruit each pixel shows (-1: background), the true instance image, their spheres and seen surfaces."""
    k = np.array([100.0, 100.0, 40.0, 30.0])
    a, b = (np.array([0.0, 0.0, 0.5]), 0.03), (np.array([0.09, 0.0, 0.5]), 0.03)
    depth, who = sphere_depth(k, (60, 80), [a, b], background_m=2.0)
    truth = np.where(who == 0, 1, np.where(who == 1, 2, 0)).astype(np.uint16)
    spheres = {1: a, 2: b}
    clouds = panoptic_fusion.surface_clouds({f: front_cap(ball) for f, ball in spheres.items()}, spheres, 0.002)
    return k, a, b, depth, who, truth, spheres, clouds


def test_a_fruit_the_render_hides_takes_back_the_pixels_on_its_seen_surface():
    k, a, b, depth, who, truth, spheres, clouds = two_seen_fruits()
    rows, cols = np.mgrid[0:60, 0:80]
    # the render paints fruit 1 as leaf but for a corner of it: it takes back every pixel on its seen surface
    hidden = (who == 0) & (rows + cols > 67)
    assert 12 < (who == 0).sum() - hidden.sum() < hidden.sum()
    inst = truth.copy()
    inst[hidden] = 0
    assert panoptic_fusion.regrow_hidden(inst, depth, k, np.eye(4), spheres, clouds, 0.01, 12) == hidden.sum()
    assert (inst == truth).all()
    # a fruit the render shows well keeps its outline as painted (here one ring short of the sensor's outline)
    ring = (who == 0) & (cv2.erode((who == 0).astype(np.uint8), np.ones((3, 3), np.uint8)) == 0)
    inst = truth.copy()
    inst[ring] = 0
    assert ring.sum() > 12 and panoptic_fusion.regrow_hidden(inst, depth, k, np.eye(4), spheres, clouds, 0.01, 12) == 0
    # a leaf 2 cm in front of the hidden part is not the fruit
    inst = truth.copy()
    inst[hidden] = 0
    leaf = np.where(hidden, depth - 0.02, depth)
    assert panoptic_fusion.regrow_hidden(inst, leaf, k, np.eye(4), spheres, clouds, 0.01, 12) == 0
    # nor is a surface 1.5 cm beyond the fruit's centre, inside its outline, where a leaf's points come within the
    # margin of the seen surface of the fruit's far side: only the half facing the camera is taken
    behind = np.where(hidden, a[0][2] + 0.015, depth)
    g = np.mgrid[-0.02:0.02:0.002, -0.02:0.02:0.002].reshape(2, -1).T
    stray = np.c_[g, np.full(len(g), a[0][2] + 0.015)]          # points a slot painted past the centre, inside
    far = panoptic_fusion.surface_clouds({1: np.concatenate([front_cap(a), stray])}, {1: a}, 0.002)
    assert (far[1].query(stray)[0] < 0.004).all()
    assert panoptic_fusion.regrow_hidden(inst, behind, k, np.eye(4), {1: a}, far, 0.01, 1) == 0
    # fewer pixels on the surface than min_px, or no margin: nothing; a fruit not in `spheres` takes nothing
    assert panoptic_fusion.regrow_hidden(inst, depth, k, np.eye(4), spheres, clouds, 0.01, hidden.sum() + 1) == 0
    assert panoptic_fusion.regrow_hidden(inst, depth, k, np.eye(4), spheres, clouds, 0.0, 12) == 0
    assert panoptic_fusion.regrow_hidden(inst, depth, k, np.eye(4), {2: b}, clouds, 0.01, 12) == 0
    assert (inst[hidden] == 0).all()
    # where two fruits' surfaces hold a pixel, the nearer takes it (fruit 4's surface lies 5 mm outside fruit 1's)
    two = {1: a, 4: (a[0], a[1] + 0.005)}
    two_clouds = {1: clouds[1], 4: panoptic_fusion.surface_clouds({4: front_cap(two[4])}, two, 0.002)[4]}
    assert panoptic_fusion.regrow_hidden(inst, depth, k, np.eye(4), two, two_clouds, 0.01, 12) == hidden.sum()
    assert (inst[hidden] == 1).all()


def test_a_fruit_the_surface_gave_pixels_outside_its_slots_span_is_regrown_there_too(tmp_path):
    k, _, _, depth, who, truth, spheres, clouds = two_seen_fruits()
    rows, cols = np.mgrid[0:60, 0:80]
    hidden = (who == 0) & (rows + cols > 67)     # painted as leaf
    corner = (who == 0) & ~hidden                # painted with the neighbour's slot
    cfg = panoptic_fusion.Config(detector_fill=False, border_band_px=0, track_margin_m=0.01)
    ctx = StageContext(stage="panoptic_fusion", seq=SEQ, data_root=tmp_path, show_progress=False)

    def fused(corner_id: int, painted: set[int] | None) -> np.ndarray:
        inst = truth.copy()
        inst[hidden], inst[corner] = 0, corner_id
        panoptic_fusion.surface_rules(inst, None, depth, k, np.eye(4), spheres, clouds, {}, cfg, ctx, painted)
        return inst

    # this frame lies outside fruit 1's slots' span (only fruit 2's slot paints here); its surface takes the
    # corner back from fruit 2, and then the hidden rest of it comes back as it does inside the span
    assert (fused(2, {2}) == truth).all()
    assert (fused(2, {1, 2}) == truth).all()
    # the corner painted as leaf and fruit 1 outside its span: nothing shows it in this frame, nothing regrows
    inst = fused(0, {2})
    assert (inst[hidden | corner] == 0).all() and (inst[who == 1] == 2).all()
    # inside the span it does regrow (the corner, on its surface, comes back with the rest); None: not run
    assert (fused(0, {1, 2})[hidden] == 1).all()
    assert (fused(2, None)[hidden] == 0).all() and (fused(2, None)[corner] == 1).all()


def test_a_later_regrow_pass_brings_back_a_fruit_on_the_surface_its_fused_frames_show(tmp_path):
    from pipeline.images import write_png
    k, a, b, depth, who, truth, _, _ = two_seen_fruits()
    cls = THING_IDS[0]
    truth = np.where(truth == 2, 300, truth)                         # the neighbour: an id past 8 bits
    spheres = {1: a, 300: b}
    x = (np.arange(80)[None] + 0.5 - k[2]) / k[0] * depth            # the row frame's x of each pixel's point
    cap = front_cap(a)
    third = a[0][0] - a[1] / 3
    points = {1: cap[cap[:, 0] < third], 300: front_cap(b)}        # fruit 1's windows rendered its left third
    left = (who == 0) & (x < third)
    assert 12 < left.sum() < ((who == 0) & ~left).sum()
    # frame 0: the rules gave fruit 1 its whole view; frame 1 shows its left third (the rest painted as leaf);
    # frames 2 and 3 show only fruit 2
    shown = [truth, np.where((who == 0) & ~left, 0, truth), np.where(who == 0, 0, truth), np.where(who == 0, 0, truth)]
    out_dir = tmp_path / "panoptic"
    for kind in ("semantic", "instance", "depth"):
        (out_dir / kind).mkdir(parents=True)
    frames = pd.DataFrame([{"frame_id": fid, "fx": k[0], "fy": k[1], "cx": k[2], "cy": k[3],
                            "depth_path": f"panoptic/depth/{fid:06d}.png", "depth_scale_m": 0.001} for fid in range(4)])
    frames = frames.set_index("frame_id", drop=False)
    depth_file = {fid: out_dir / "depth" / f"{fid:06d}.png" for fid in range(4)}
    cams = {fid: np.eye(4) for fid in range(4)}
    cfg = panoptic_fusion.Config(track_margin_m=0.01, regrow_passes=2)
    ctx = StageContext(stage="panoptic_fusion", seq=SEQ, data_root=tmp_path, show_progress=False)
    # on the surface its windows rendered, frame 1's hidden two thirds lie off it: the first pass gives nothing
    first = panoptic_fusion.seen_surfaces(points, spheres, cfg)
    assert panoptic_fusion.regrow_hidden(shown[1].copy(), depth, k, np.eye(4), spheres, first, 0.01, 12) == 0

    def regrown(balls: dict, off_sensor: dict, config=cfg) -> tuple[list[np.ndarray], list[dict]]:
        rows = []
        for fid, inst in enumerate(shown):
            name = f"{fid:06d}.png"
            write_png(out_dir / "instance" / name, inst.astype(np.uint16))
            write_png(out_dir / "semantic" / name, np.where(inst > 0, cls, 1).astype(np.uint8))
            write_png(out_dir / "depth" / name, np.round(depth * 1000).astype(np.uint16))
            rows.append({"frame_id": fid, "n_fruits": len(np.unique(inst[inst > 0]))})
        ctx.summary.clear()
        panoptic_fusion.regrow_on_fused(rows, depth_file, cams, points, balls, off_sensor,
                                        np.r_[0, np.full(300, cls)].astype(np.uint8), frames, out_dir, config, ctx)
        return [read_label(out_dir / kind / f"{fid:06d}.png", kind) for kind in ("instance", "semantic")
                for fid in range(4)], rows

    # a fruit whose render lies off the sensor's surface is left out: nothing changes
    assert all((got == want).all() for got, want in zip(regrown(spheres, {1: np.zeros(3)})[0][:4], shown))
    # the second pass adds frame 0's view to fruit 1's surface: frame 1 gets the rest of it back, with its
    # class, and so does frame 2, the one after the last that shows it (a fruit leaving the view, or lost
    # behind a leaf for a frame); frame 3, further on, stays without it. So it does for a fruit without a
    # sphere (its render points fit none), which takes the sphere its grown points fit
    for balls in (spheres, {300: b}):
        (inst0, inst1, inst2, inst3, _, sem1, sem2, _), rows = regrown(balls, {})
        assert (inst0 == truth).all() and (inst1 == truth).all() and (inst2 == truth).all()
        assert (inst3 == shown[3]).all() and (sem1[who == 0] == cls).all() and (sem2[who == 0] == cls).all()
        assert ctx.summary["pixels_regrown_on_grown_surfaces"] == (shown[1] != truth).sum() + (who == 0).sum()
        assert [r["n_fruits"] for r in rows] == [2, 2, 2, 1]
    # but not where its grown points fit no plausible sphere (here: none of a fruit's size is allowed)
    small = panoptic_fusion.Config(track_margin_m=0.01, regrow_passes=2, max_fruit_radius_m=0.02)
    assert all((got == want).all() for got, want in zip(regrown({300: b}, {}, small)[0][:4], shown))
    with pytest.raises(ValueError, match="regrow_passes"):
        panoptic_fusion.Config(regrow_passes=0)


def test_a_fruit_cut_off_by_the_image_edge_takes_its_sliver_there_from_its_seen_surface():
    k = np.array([100.0, 100.0, 40.0, 30.0])
    a, b = (np.array([-0.2, 0.0, 0.5]), 0.03), (np.array([0.0, 0.0, 0.5]), 0.03)  # a: cut off by the left edge
    c = (np.array([0.1, -0.15, 0.5]), 0.03)                                        # c: cut off by the top edge
    depth, who = sphere_depth(k, (60, 80), [a, b, c], background_m=2.0)
    truth = np.where(who == 0, 1, np.where(who == 1, 2, np.where(who == 2, 5, 0))).astype(np.uint16)
    cols, rows = np.arange(80)[None], np.arange(60)[:, None]
    sliver, inner = (who == 0) & (cols < 4), (who == 1) & (cols < 38)     # painted as leaf by the render
    top = (who == 2) & (rows < 4)
    assert sliver.sum() > 10 and inner.sum() > 10 and top.sum() > 10
    inst = truth.copy()
    inst[sliver | inner | top] = 0
    spheres = {1: a, 2: b, 3: (np.array([2.0, 0.0, 0.5]), 0.03), 5: c}     # fruit 3 is out of view
    # the seen surface is what the windows saw inside the fruit's sphere: a leaf 2 cm behind fruit 1's outline
    # that its slot painted stays out of it
    leaf = a[0] + np.array([-a[1] - 0.005, 0.0, 0.02]) + np.random.default_rng(1).normal(0, 0.002, (50, 3))
    seen = {f: front_cap(ball) for f, ball in spheres.items()}
    seen[1] = np.concatenate([seen[1], leaf])
    clouds = panoptic_fusion.surface_clouds(seen, spheres, 0.002)
    assert set(clouds) == {1, 2, 3, 5} and (clouds[1].query(leaf)[0] > 0.01).all()
    # only the band along the edges is given: fruit 2's pixels in the middle keep the render's label
    given = panoptic_fusion.border_surfaces(inst, depth, k, np.eye(4), spheres, clouds, 0.01, 4)
    assert given == sliver.sum() + top.sum()
    assert (inst[sliver] == 1).all() and (inst[top] == 5).all() and (inst[inner] == 0).all()
    assert (inst[who == -1] == 0).all()
    inst[top] = 0
    del spheres[5]
    before = inst.copy()
    before[sliver] = 0
    assert panoptic_fusion.border_surfaces(inst, depth, k, np.eye(4), spheres, clouds, 0.01, 4) == 0   # done
    # the sliver painted with the neighbour's slot goes back to the fruit whose surface holds it
    inst[sliver] = 2
    assert panoptic_fusion.border_surfaces(inst, depth, k, np.eye(4), spheres, clouds, 0.01, 4) == sliver.sum()
    assert (inst[sliver] == 1).all()
    # a leaf 2 cm in front of the fruit, and one 1.5 cm beyond its outline behind it, are not taken
    v, u = np.mgrid[0:60, 0:80]
    ray = np.stack([(u + 0.5 - k[2]) / k[0], (v + 0.5 - k[3]) / k[1], np.ones((60, 80))], -1)
    unit = ray / np.linalg.norm(ray, axis=-1, keepdims=True)
    along = unit @ a[0]
    beside = np.linalg.norm(along[..., None] * unit - a[0], axis=-1)
    behind = (who == -1) & (cols < 4) & (beside < a[1] + 0.003)
    assert behind.sum() > 3
    leaves = np.where(sliver, depth - 0.02, np.where(behind, (along + 0.015) * unit[..., 2], depth))
    inst = before.copy()
    assert panoptic_fusion.border_surfaces(inst, leaves, k, np.eye(4), spheres, clouds, 0.01, 4) == 0
    # where two fruits' surfaces hold a point, the nearer takes it (fruit 4's surface lies 5 mm outside fruit
    # 1's, around the same centre), but a pixel stays with its own fruit where that fruit's surface holds it
    two = {1: a, 4: (a[0], a[1] + 0.005)}
    two_clouds = {1: clouds[1], 4: panoptic_fusion.surface_clouds({4: front_cap(two[4])}, two, 0.002)[4]}
    assert panoptic_fusion.border_surfaces(inst, depth, k, np.eye(4), two, two_clouds, 0.01, 4) == sliver.sum()
    assert (inst[sliver] == 1).all()
    inst[sliver] = 4
    assert panoptic_fusion.border_surfaces(inst, depth, k, np.eye(4), two, two_clouds, 0.01, 4) == 0
    # a sphere wider than the fruit (fitted to an elongated fruit: here 2 cm wider, its centre 1 cm deeper)
    # passes well in front of the fruit's sides, where the sliver is, so no point of the sliver lies on its
    # front surface; the fruit's seen surface still holds the sliver
    wide = {1: (a[0] + np.array([0.0, 0.0, 0.01]), a[1] + 0.02)}
    wide_clouds = panoptic_fusion.surface_clouds({1: front_cap(a)}, wide, 0.002)
    inst = before.copy()
    assert panoptic_fusion.border_surfaces(inst, depth, k, np.eye(4), wide, wide_clouds, 0.01, 4) == sliver.sum()
    assert (inst[sliver] == 1).all()
    inst[sliver] = 4
    # a fruit without a seen surface gives the pixels on another's surface to it
    assert panoptic_fusion.border_surfaces(inst, depth, k, np.eye(4), two, {1: clouds[1]}, 0.01, 4) == sliver.sum()
    assert (inst[sliver] == 1).all()
    # no band, no margin or no surfaces: nothing
    for band, margin, balls in ((0, 0.01, spheres), (4, 0.0, spheres), (4, 0.01, {})):
        inst = before.copy()
        assert panoptic_fusion.border_surfaces(inst, depth, k, np.eye(4), balls, clouds, margin, band) == 0
        assert panoptic_fusion.border_surfaces(inst, depth, k, np.eye(4), spheres, {}, margin, band) == 0
    with pytest.raises(ValueError, match="border_band_px"):
        panoptic_fusion.Config(border_band_px=-1)


def test_the_detector_shows_a_fused_fruit_as_two_when_two_lasting_clusters_share_a_frame():
    x, y = np.array([0.0, 0.6, 0.8]), np.array([0.08, 0.6, 0.8])   # two touching fruits' seen-surface centres
    jitter = np.random.default_rng(0).normal(0, 0.003, (40, 3))

    def view(frame, seg, px, centre, i):
        return (frame, seg, px, centre + jitter[i], np.zeros((0, 3)))

    # frames 0-5 show x, frames 2-4 also y: two fruits, x (more pixels) first
    views = [view(f, 1, 500, x, f) for f in range(6)] + [view(f, 2, 100, y, 10 + f) for f in range(2, 5)]
    labels, centres = panoptic_fusion.detector_clusters(views, 0.03, 2)
    assert list(labels) == [0] * 6 + [1] * 3
    assert np.linalg.norm(centres[0] - x) < 0.005 and np.linalg.norm(centres[1] - y) < 0.005
    # one fruit whose seen-surface centre drifts 2 cm a frame (entering the view) is one fruit
    drift = [view(f, 1, 300, x + [0.02 * f, 0, 0], f) for f in range(5)]
    assert panoptic_fusion.detector_clusters(drift, 0.03, 2)[1] == []
    # two clusters never seen in one frame (a fruit seen first from one side, then from the other): one fruit
    apart = [view(f, 1, 500, x, f) for f in range(3)] + [view(f, 1, 500, y, 10 + f) for f in range(3, 6)]
    assert panoptic_fusion.detector_clusters(apart, 0.03, 2)[1] == []
    # the second fruit in one frame only is not enough with min_frames 2; a segment merging both (its centre
    # half-way) links nothing
    once = [view(f, 1, 500, x, f) for f in range(6)] + [view(3, 2, 100, y, 20), view(4, 3, 600, (x + y) / 2, 21)]
    labels, centres = panoptic_fusion.detector_clusters(once, 0.03, 2)
    assert centres == [] and (labels == -1).all()
    assert len(panoptic_fusion.detector_clusters(once, 0.03, 1)[1]) == 3
    # ... but it is where the second cluster lies off the fused fruit's sphere (3D evidence for a fruit seen once
    # at the row's end); a cluster on the sphere still needs min_frames shared frames
    ball = (x + np.array([0.0, 0.0, 0.03]), 0.045)
    off = lambda c: float(np.linalg.norm(c - ball[0])) > ball[1] + 0.01   # noqa: E731
    assert off(y) and not off(x) and not off((x + y) / 2)
    labels, centres = panoptic_fusion.detector_clusters(once, 0.03, 2, off)
    assert list(labels) == [0] * 6 + [1, -1] and np.linalg.norm(centres[1] - y) < 0.01
    near = [view(f, 1, 500, x, f) for f in range(6)] + [view(3, 2, 100, x + [0.035, 0, 0], 22)]
    assert not off(x + [0.035, 0, 0]) and panoptic_fusion.detector_clusters(near, 0.03, 2, off)[1] == []
    assert len(panoptic_fusion.detector_clusters(near, 0.03, 2, lambda c: None)[1]) == 2   # no sphere: not on it
    # clusters never seen in one frame: one fruit without a sphere, two where one lies off the fruit's sphere (a
    # fruit seen in the last frame alone, where the detector missed the fruit whose id it was painted with)
    assert panoptic_fusion.detector_clusters(apart, 0.03, 2, lambda c: None)[1] == []
    assert panoptic_fusion.detector_clusters(apart, 0.03, 2, lambda c: False)[1] == []
    labels, centres = panoptic_fusion.detector_clusters(apart, 0.03, 2, off)
    assert list(labels) == [0] * 3 + [1] * 3 and np.linalg.norm(centres[1] - y) < 0.01
    assert panoptic_fusion.detector_clusters(views, 0.0, 2)[1] == []
    with pytest.raises(ValueError, match="detector_split_m"):
        panoptic_fusion.Config(detector_split_m=-0.01)


def test_a_fused_fruit_split_by_the_detector_hands_its_pixels_to_the_fruits_it_holds():
    k = np.array([100.0, 100.0, 40.0, 30.0])
    a, b = (np.array([-0.03, 0.0, 0.5]), 0.03), (np.array([0.035, 0.0, 0.52]), 0.035)    # touching fruits
    depth, who = sphere_depth(k, (60, 80), [a, b], background_m=2.0)
    inst = np.where(who >= 0, 4, 0).astype(np.uint16)             # the render painted both with fruit 4
    segments = np.where(who == 0, 8, np.where(who == 1, 9, 0))
    segments[(who == 1) & (np.arange(80)[None] > 50)] = 0          # the detector's mask of b is partial
    views = panoptic_fusion.segment_centres(inst, segments, depth, k, np.eye(4), min_px=10, max_points=50)
    assert sorted((f, s) for f, s, *_ in views) == [(4, 8), (4, 9)]
    assert all(len(v[4]) <= 50 for v in views)
    stuff = segments.copy()
    stuff[who < 0] = 9                                             # segment 9 lies mostly on the background
    views = panoptic_fusion.segment_centres(inst, stuff, depth, k, np.eye(4), min_px=10, max_points=50)
    assert [(f, s) for f, s, *_ in views] == [(4, 8)]
    moved = panoptic_fusion.split_by_detector(inst, segments, depth, k, np.eye(4), 4, [4, 12], [a, b],
                                              {8: 0, 9: 1}, min_px=10)
    assert moved == (who == 1).sum()
    assert (inst[who == 0] == 4).all() and (inst[who == 1] == 12).all() and (inst[who < 0] == 0).all()
    # a frame without b's segment: b's pixels still go to its sphere, being many; a few stray pixels do not
    inst = np.where(who >= 0, 4, 0).astype(np.uint16)
    only_a = np.where(who == 0, 8, 0)
    panoptic_fusion.split_by_detector(inst, only_a, depth, k, np.eye(4), 4, [4, 12], [a, b], {8: 0}, min_px=10)
    assert (inst[who == 1] == 12).all()
    inst = np.where(who >= 0, 4, 0).astype(np.uint16)
    few = (who == 1) & (np.cumsum(who == 1, axis=None).reshape(who.shape) <= 5)
    inst[(who == 1) & ~few] = 0
    assert panoptic_fusion.split_by_detector(inst, only_a, depth, k, np.eye(4), 4, [4, 12], [a, b], {8: 0},
                                             min_px=10) == 0
    # without spheres (a cluster without a plausible fit) the pixels go to the nearest seen surface (the points
    # of each cluster's segments); a cluster without a segment in the frame takes only those on its surface
    v, u = np.nonzero(who >= 0)
    pts = panoptic_fusion.unproject(depth, k, np.eye(4), v, u)
    on_a, on_b = who[v, u] == 0, who[v, u] == 1
    surfaces = [cKDTree(pts[on_a]), cKDTree(pts[on_b])]
    inst = np.where(who >= 0, 4, 0).astype(np.uint16)
    moved = panoptic_fusion.split_by_detector(inst, segments, depth, k, np.eye(4), 4, [4, 12], None, {8: 0, 9: 1},
                                              10, surfaces, 0.01)
    assert moved == (who == 1).sum() and (inst[who == 0] == 4).all() and (inst[who == 1] == 12).all()
    seen_b = on_b & (u < 48)                       # b seen so far: its left part only
    surfaces = [cKDTree(pts[on_a]), cKDTree(pts[seen_b])]
    gap = surfaces[1].query(pts)[0]
    near_b = on_b & (gap <= 0.01)
    assert near_b.sum() > seen_b.sum() and (on_b & ~near_b).sum() > 10
    inst = np.where(who >= 0, 4, 0).astype(np.uint16)
    moved = panoptic_fusion.split_by_detector(inst, only_a, depth, k, np.eye(4), 4, [4, 12], None, {8: 0},
                                              10, surfaces, 0.01)
    assert moved == near_b.sum() and (inst[v[near_b], u[near_b]] == 12).all()
    assert (inst[v[~near_b], u[~near_b]] == 4).all()
    # with spheres, pixels on a cluster's seen surface go to that cluster first: b's sliver (fewer than min_px,
    # no segment of b in the frame) joins b, and b's pixels leave a sphere fitted too wide for a, which holds
    # them deeper than b's (a sphere fitted to an elongated fruit seen from one side)
    surfaces = [cKDTree(pts[on_a]), cKDTree(pts[on_b])]
    inst = np.where(who >= 0, 4, 0).astype(np.uint16)
    inst[(who == 1) & ~few] = 0
    assert panoptic_fusion.split_by_detector(inst, only_a, depth, k, np.eye(4), 4, [4, 12], [a, b], {8: 0}, 10,
                                             surfaces, 0.01) == few.sum()
    assert (inst[few] == 12).all() and (inst[who == 0] == 4).all()
    wide = (a[0] + [0.02, 0.0, 0.0], 0.07)
    inst = np.where(who >= 0, 4, 0).astype(np.uint16)
    panoptic_fusion.split_by_detector(inst, only_a, depth, k, np.eye(4), 4, [4, 12], [wide, b], {8: 0}, min_px=10)
    assert (inst[who == 1] == 4).sum() > 10                        # by the spheres alone b's pixels stay with a
    inst = np.where(who >= 0, 4, 0).astype(np.uint16)
    moved = panoptic_fusion.split_by_detector(inst, only_a, depth, k, np.eye(4), 4, [4, 12], [wide, b], {8: 0}, 10,
                                              surfaces, 0.01)
    assert moved == (who == 1).sum() and (inst[who == 1] == 12).all() and (inst[who == 0] == 4).all()
    with pytest.raises(ValueError, match="spheres or their seen surfaces"):
        panoptic_fusion.split_by_detector(inst, only_a, depth, k, np.eye(4), 4, [4, 12], None, {8: 0}, 10)


def test_split_fruits_rewrites_the_fused_frames_of_a_fruit_painted_over_two(tmp_path):
    from pipeline.images import write_png
    k = np.array([100.0, 100.0, 40.0, 30.0])
    a, b = (np.array([-0.03, 0.0, 0.5]), 0.03), (np.array([0.035, 0.0, 0.52]), 0.035)    # touching fruits
    depth, who = sphere_depth(k, (60, 80), [a, b], background_m=2.0)
    cls = THING_IDS[0]
    out_dir = tmp_path / "panoptic"
    rows, frames = [], []
    for fid in range(3):
        name = f"{fid:06d}.png"
        det = np.where(who == 0, 8, 9) * (who >= 0)
        for kind, img in (("semantic", np.where(who >= 0, cls, 1)), ("instance", np.where(who >= 0, 4, 0)),
                          ("det_sem", np.where(who >= 0, cls, 1)), ("det_inst", det)):
            (tmp_path / kind).mkdir(exist_ok=True)
            write_png(tmp_path / kind / name, img.astype(np.uint16 if "inst" in kind else np.uint8))
        (tmp_path / "depth").mkdir(exist_ok=True)
        write_png(tmp_path / "depth" / name, np.round(depth * 1000).astype(np.uint16))
        rows.append({"frame_id": fid, "n_fruits": 1})
        frames.append({"frame_id": fid, "height": 60, "width": 80, "fx": k[0], "fy": k[1], "cx": k[2], "cy": k[3],
                       "depth_path": f"depth/{name}", "depth_scale_m": 0.001, "det_semantic_path": f"det_sem/{name}",
                       "det_instance_path": f"det_inst/{name}"})
    frames = pd.DataFrame(frames).set_index("frame_id", drop=False)
    cfg = panoptic_fusion.Config()

    def run(fruit_centres, n_ids):
        out_dir.mkdir(exist_ok=True)
        for kind in ("semantic", "instance"):
            (out_dir / kind).mkdir(exist_ok=True)
            for fid in range(3):
                (out_dir / kind / f"{fid:06d}.png").write_bytes((tmp_path / kind / f"{fid:06d}.png").read_bytes())
        seg_views = {4: []}
        for fid in range(3):
            segs = fruit_segments(frames.loc[fid], tmp_path)
            for f, *view in panoptic_fusion.segment_centres(np.where(who >= 0, 4, 0), segs, depth, k, np.eye(4),
                                                            cfg.min_group_px, cfg.max_points_per_view):
                seg_views[f].append((fid, *view))
        ctx = StageContext(stage="panoptic_fusion", seq=SEQ, data_root=tmp_path, show_progress=False)
        n, spheres, _, classes = panoptic_fusion.split_fruits(
            seg_views, {f: {4} for f in range(3)}, {f: tmp_path / "depth" / f"{f:06d}.png" for f in range(3)},
            {f: np.eye(4) for f in range(3)}, rows, {}, {}, set(), fruit_centres, np.full(n_ids + 1, cls, np.uint8),
            frames, {}, out_dir, cfg, ctx)
        assert len(classes) == n + 1 and (classes[1:] == cls).all()
        return n, [read_label(out_dir / "instance" / f"{f:06d}.png", "x") for f in range(3)], ctx.summary, spheres

    # fruit 4 (no plausible sphere: it holds two fruits) keeps the larger, the other becomes fruit 5
    n, insts, summary, spheres = run({4: (a[0] + b[0]) / 2}, 4)
    # both clusters fit a sphere: fruit 4 and the new fruit 5 take theirs (for the later rules and passes)
    assert sorted(spheres) == [4, 5]
    assert n == 5 and summary["fruits_split_by_detector"] == 1 and [r["n_fruits"] for r in rows] == [2, 2, 2]
    big = 4 if (who == 0).sum() > (who == 1).sum() else 5
    for inst in insts:
        assert (inst[who == 0] == (4 if big == 4 else 5)).all() and (inst[who == 1] == (5 if big == 4 else 4)).all()
        assert (inst[who < 0] == 0).all()
    # where another fruit's centre lies at the split-off cluster's sphere, the cluster joins that fruit
    other = 1 if big == 4 else 0
    # a new fruit past id 255 keeps its id in the rewritten 16-bit PNGs
    n, insts, _, _ = run({4: (a[0] + b[0]) / 2}, 299)
    assert n == 300 and all(set(np.unique(inst[who >= 0]).tolist()) == {4, 300} for inst in insts)
    n, insts, _, spheres = run({4: (a[0] + b[0]) / 2, 6: (a, b)[other][0] + 0.01}, 6)
    assert n == 6 and sorted(spheres) == [4, 6] and all(set(np.unique(inst[who == other])) == {6} for inst in insts)


def test_the_detector_fruit_segments_leave_out_stuff_and_the_segments_the_depth_filter_dropped(tmp_path):
    sem = np.full((4, 6), 1, np.uint8)
    inst = np.zeros((4, 6), np.uint16)
    sem[:, :2], inst[:, :2] = THING_IDS[0], 3              # a kept fruit segment
    sem[:, 2:4], inst[:, 2:4] = THING_IDS[0], 4            # one the depth filter dropped (the far row)
    inst[:, 4:] = 5                                        # an id on stuff pixels
    cv2.imwrite(str(tmp_path / "s.png"), sem)
    cv2.imwrite(str(tmp_path / "i.png"), inst)
    frame = pd.Series({"frame_id": 7, "width": 6, "height": 4, "det_semantic_path": "s.png",
                       "det_instance_path": "i.png"})
    dets = pd.DataFrame({"frame_id": [7, 7, 8], "segment_id": [3, 4, 3], "kept": [True, False, False]})
    dropped = dropped_segments(dets)
    assert sorted(dropped) == [7, 8] and list(dropped[7]) == [4]
    seg = fruit_segments(frame, tmp_path, dropped.get(7))
    assert (seg[:, :2] == 3).all() and (seg[:, 2:] == 0).all()
    assert fruit_segments(frame.copy().replace({"s.png": None}), tmp_path) is None   # no detector output
    with pytest.raises(ImageError, match="detector PNGs"):
        fruit_segments(frame.copy().replace({6: 5}), tmp_path)


def test_a_piece_the_render_misplaces_is_given_back_by_the_sensor_depth(make_row, tiny_row_upstream):
    # in one frame a single window rendered, a third of the largest fruit is painted with another fruit's
    # slot and rendered at the far background (as a render can be at the image border); the recorded depth
    # still lies on the fruit's own surface
    frames = pd.read_parquet(tiny_row_upstream / "interim" / SEQ / "frames.parquet").set_index("frame_id")
    windows = pd.read_parquet(tiny_row_upstream / "interim" / SEQ / "windows.parquet")
    val = windows[windows.split == "val"]
    alone = val.groupby("frame_id").window_id.nunique().loc[lambda n: n == 1].index
    gt = {int(f): read_label(tiny_row_upstream / frames.loc[f, "gt_instance_path"], "gt") for f in alone}
    fid = max(gt, key=lambda f: np.bincount(gt[f].ravel())[1:].max(initial=0))
    wid = int(val[val.frame_id == fid].window_id.iloc[0])
    g_inst = gt[fid]
    ids, n = np.unique(g_inst[g_inst > 0], return_counts=True)
    assert len(ids) >= 2, "the chosen frame shows fewer than two fruits"
    a, b = int(ids[np.argmax(n)]), int(ids[np.argsort(n)[-2]])
    cols = np.nonzero((g_inst == a).any(0))[0]
    stolen = (g_inst == a) & (np.arange(g_inst.shape[1])[None] > cols.min() + 2 * (cols.max() - cols.min()) / 3)
    assert stolen.sum() >= 10

    def steal(w: int, f: int, sem: np.ndarray, slots: np.ndarray):
        if (w, f) == (wid, fid):
            slots = slots.copy()
            slots[stolen] = slots[g_inst == b][0]
        return sem, slots

    row = make_row(hook=steal)
    depth_png = row.processed / "nerf" / file_name(wid, "depth", fid)
    rendered = cv2.imread(str(depth_png), cv2.IMREAD_UNCHANGED)
    rendered[stolen] = 3000                                  # mm: on no fruit's sphere
    cv2.imwrite(str(depth_png), rendered)
    pieces = {}
    for which in ("sensor", "rendered"):
        row.runner(f"panoptic_fusion.surface_depth={which}").run(["panoptic_fusion"], force=True)
        pf = pd.read_parquet(row.processed / "panoptic_frames.parquet").set_index("frame_id")
        fused = read_label(row.root / pf.loc[fid, "instance_path"], "fused")
        own = np.bincount(fused[(g_inst == a) & ~stolen]).argmax()
        pieces[which] = (fused[stolen] == own).mean()
    assert pieces["sensor"] >= 0.9 and pieces["rendered"] <= 0.1, pieces


def test_each_fruit_of_a_frame_several_windows_rendered_comes_from_the_window_that_saw_it_best():
    h, w = 8, 12
    near_inst, other_inst = np.zeros((h, w), np.uint16), np.zeros((h, w), np.uint16)
    near_sem, other_sem = np.full((h, w), 1, np.uint8), np.full((h, w), 0, np.uint8)
    near_inst[0:4, 0:2] = 5                 # fruit 5: a sliver in the nearest window, which saw it in 2 frames
    other_inst[0:4, 0:5] = 5                # ... and whole in the other window, which saw it in 9
    near_inst[4:8, 4:8] = 6                 # fruit 6: only the nearest window shows it here
    other_inst[5:8, 6:10] = 7               # fruit 7: only the other window; it overlaps fruit 6's pixels
    near_sem[near_inst > 0], other_sem[other_inst > 0] = 3, 2
    near_depth, other_depth = np.full((h, w), 1.0, np.float32), np.full((h, w), 2.0, np.float32)
    support = {(0, 5): (2, 8), (1, 5): (9, 180), (0, 6): (4, 60), (1, 7): (3, 40)}
    sem, inst, depth, composed = panoptic_fusion.compose(
        [(near_sem, near_inst, near_depth), (other_sem, other_inst, other_depth)], [0, 1], support)
    assert composed
    assert (inst[0:4, 0:5] == 5).all() and (depth[0:4, 0:5] == 2.0).all() and (sem[0:4, 0:5] == 2).all()
    assert (inst[4:8, 4:8] == 6).all() and (depth[4:8, 4:8] == 1.0).all()    # the nearest window wins overlaps
    assert (inst == 7).sum() == (other_inst == 7).sum() - 6                  # the rest of fruit 7 is kept
    stuff = inst == 0
    assert (sem[stuff] == 1).all() and (depth[stuff] == 1.0).all()          # stuff from the nearest window
    # equal support: the nearest window keeps its pixels; one window: its labels as they are
    tie = {**support, (1, 5): (2, 8)}
    assert (panoptic_fusion.compose([(near_sem, near_inst, near_depth), (other_sem, other_inst, other_depth)],
                                    [0, 1], tie)[1] == 5).sum() == 8
    sem1, inst1, depth1, composed1 = panoptic_fusion.compose([(near_sem, near_inst, near_depth)], [0], support)
    assert not composed1 and (inst1 == near_inst).all() and (sem1 == near_sem).all()


def test_a_frame_the_nearest_window_rendered_without_its_fruits_takes_them_from_the_other_window(
        make_row, tiny_row_upstream):
    windows = pd.read_parquet(tiny_row_upstream / "interim" / SEQ / "windows.parquet")
    val = windows[windows.split == "val"].assign(d=lambda t: t.offset.abs()).sort_values(["frame_id", "d", "window_id"])
    shared = val.groupby("frame_id").window_id.nunique().loc[lambda n: n > 1].index
    nearest = {int(f): int(val[val.frame_id == f].window_id.iloc[0]) for f in shared}
    assert nearest, "the tiny row's windows share no rendered frame"

    def lose_fruits(wid: int, fid: int, sem: np.ndarray, slots: np.ndarray):
        if nearest.get(fid) == wid:
            sem, slots = np.where(slots > 0, 1, sem), np.zeros_like(slots)
        return sem, slots

    # the fruit pixels the windows rendered, nothing added
    render_only = ("panoptic_fusion.detector_fill=false", "panoptic_fusion.border_band_px=0",
                   "panoptic_fusion.regrow_min_px=0")
    whole = make_row(name="whole")
    whole.runner(*render_only).run(["panoptic_fusion"], force=True)
    row = make_row(hook=lose_fruits)
    row.runner(*render_only).run(["panoptic_fusion"], force=True)
    pf = pd.read_parquet(row.processed / "panoptic_frames.parquet").set_index("frame_id")
    pf_whole = pd.read_parquet(whole.processed / "panoptic_frames.parquet").set_index("frame_id")
    n_fruit_px = 0
    for f in nearest:
        fused = read_label(row.root / pf.loc[f, "instance_path"], "fused")
        expected = read_label(whole.root / pf_whole.loc[f, "instance_path"], "fused")
        # every fruit pixel, from the other window (up to a few pixels the surface rule moves differently)
        assert ((fused > 0) != (expected > 0)).sum() <= 0.01 * (expected > 0).sum()
        n_fruit_px += int((fused > 0).sum())
        if (fused > 0).any():
            assert pf.loc[f, "window_id"] == nearest[f] and "panoptic/depth/" in pf.loc[f, "depth_path"]
            assert (row.root / pf.loc[f, "depth_path"]).exists()
    assert n_fruit_px > 0
    row.runner("panoptic_fusion.compose_shared_frames=false", *render_only).run(["panoptic_fusion"], force=True)
    pf = pd.read_parquet(row.processed / "panoptic_frames.parquet").set_index("frame_id")
    assert all((read_label(row.root / pf.loc[f, "instance_path"], "fused") == 0).all() for f in nearest)


def drop_renders(row, kinds: tuple[str, ...], window: int | None = None) -> None:
    """Remove renders of `kinds` (of one window, or all) from disk and from renders.parquet."""
    table = pd.read_parquet(row.processed / "renders.parquet")
    gone = table.kind.isin(kinds) & ((table.window_id == window) if window is not None else True)
    for p in table.path[gone]:
        (row.root / p).unlink()
    table[~gone].to_parquet(row.processed / "renders.parquet")


def test_failed_and_unrendered_windows_are_skipped_with_a_note(make_row):
    row = make_row()
    m = pd.read_parquet(row.processed / "window_metrics.parquet")
    m.loc[m.window_id == 2, ["status", "error"]] = ["failed", "step 3: non-finite loss"]
    m.to_parquet(row.processed / "window_metrics.parquet")
    drop_renders(row, ("semantic", "instance"), window=1)         # window 1 without the panoptic phase
    res = row.runner().run(["panoptic_fusion"], force=True)[0]
    assert res.summary["windows_failed_skipped"] == 1 and res.summary["windows_without_panoptic_renders"] == 1
    assert any("window 2 failed" in n for n in res.summary["notes"])
    pf = pd.read_parquet(row.processed / "panoptic_frames.parquet")
    assert set(pf.window_id) == {0}


def test_a_missing_render_is_an_error_naming_the_file(make_row):
    row = make_row()
    table = pd.read_parquet(row.processed / "renders.parquet")
    victim = table[(table.window_id == 0) & (table.kind == "instance")].path.iloc[1]
    (row.root / victim).unlink()
    with pytest.raises(ImageError, match=Path(victim).name):
        row.runner().run(["panoptic_fusion"], force=True)


def test_a_render_the_table_does_not_list_is_an_error_naming_window_frame_and_kind(make_row):
    row = make_row()
    table = pd.read_parquet(row.processed / "renders.parquet")
    drop = table[(table.window_id == 0) & (table.kind == "depth")].index[1]
    frame = int(table.frame_id[drop])
    table.drop(index=drop).to_parquet(row.processed / "renders.parquet")
    with pytest.raises(ImageError, match=f"window 0, validation frame {frame}: renders.parquet lists no depth"):
        row.runner().run(["panoptic_fusion"], force=True)


# -- fruit_count -----------------------------------------------------------------------------------------

def test_fruit_positions_and_diameters_are_near_ground_truth(perfect_row):
    g2f, _, px = gt_to_fused(perfect_row)
    fruits = pd.read_parquet(perfect_row.processed / "fruits.parquet").set_index("fruit_id")
    gt = perfect_row.gt_fruits.set_index("fruit_id")
    pairs = [(g, next(iter(f - {0}))) for g, f in g2f.items() if len(f - {0}) == 1 and px[g] >= 400]
    assert len(pairs) >= 4
    near = [(g, f) for g, f in pairs if gt.loc[g, "near_row"]]
    assert near and all(fruits.loc[f, "near_row"] for _, f in near)
    assert all(not fruits.loc[f, "near_row"] for g, f in pairs if not gt.loc[g, "near_row"])
    gi, fi = (list(v) for v in zip(*near))
    err = np.linalg.norm(fruits.loc[fi, ["x_m", "y_m", "z_m"]].to_numpy() - gt.loc[gi, ["x_m", "y_m", "z_m"]].to_numpy(),
                         axis=1)
    assert np.median(err) < 0.015, err
    dia = {k: np.abs(fruits.loc[fi, k].to_numpy() - gt.loc[gi, "diameter_m"].to_numpy())
           for k in ("diameter_m", "diameter_sphere_m", "diameter_pca_m")}
    assert np.median(dia["diameter_m"]) < 0.01, dia
    # the spheroid fit beats the sphere fit and the principal extents on peppers
    assert dia["diameter_m"].mean() < dia["diameter_sphere_m"].mean()
    assert dia["diameter_m"].mean() < dia["diameter_pca_m"].mean()
    assert (fruits.loc[fi, "class_id"].to_numpy() == gt.loc[gi, "class_id"].to_numpy()).all()
    assert (fruits.class_confidence.between(0, 1)).all() and (fruits.n_frames >= 1).all()
    assert (fruits.first_frame_id <= fruits.last_frame_id).all()


def test_fruit_centres_and_sizes_come_from_the_sensor_depth_where_the_render_is_off(make_row):
    row = make_row()
    table = pd.read_parquet(row.processed / "renders.parquet")
    for p in table.path[table.kind == "depth"]:               # every depth render 8 % too near: 4 cm at 0.5 m
        img = cv2.imread(str(row.root / p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(row.root / p), (img * 0.92).astype(np.uint16))
    gt = row.gt_fruits[row.gt_fruits.near_row.astype(bool)]
    errors = {}
    for which in ("sensor", "rendered"):
        row.runner("panoptic_fusion.surface_depth=rendered", f"fruit_count.surface_depth={which}").run(
            ["panoptic_fusion", "fruit_count"], force=True)
        fruits = pd.read_parquet(row.processed / "fruits.parquet")
        fruits = fruits[fruits.counted.astype(bool)]
        d = np.linalg.norm(fruits[["x_m", "y_m", "z_m"]].to_numpy()[:, None] - gt[["x_m", "y_m", "z_m"]].to_numpy()[None],
                           axis=2)
        near = d.argmin(1)
        errors[which] = (np.median(d.min(1)),
                         np.median(np.abs(fruits.diameter_m.to_numpy() - gt.diameter_m.to_numpy()[near])))
    assert errors["sensor"][0] < 0.015 and errors["rendered"][0] > 0.025, errors
    assert errors["sensor"][1] < errors["rendered"][1], errors


def test_the_sensor_depth_fills_in_where_it_is_valid_and_must_match_the_render(tmp_path):
    sensor = np.array([[0, 500], [1200, 0]], np.uint16)                     # mm; 0 = no depth
    cv2.imwrite(str(tmp_path / "d.png"), sensor)
    rendered = np.full((2, 2), 0.7, np.float32)
    assert np.allclose(with_sensor_depth(rendered, tmp_path / "d.png", 0.001), [[0.7, 0.5], [1.2, 0.7]])
    with pytest.raises(ImageError, match="d.png is 2x2 but the render is 3x2"):
        with_sensor_depth(np.zeros((2, 3), np.float32), tmp_path / "d.png", 0.001)


def test_counts_equal_the_ground_truth_near_row_fruits_seen(perfect_row):
    _, _, px = gt_to_fused(perfect_row)
    gt = perfect_row.gt_fruits.set_index("fruit_id")
    seen = [g for g, n in px.items() if n >= 4 and gt.loc[g, "near_row"]]
    counts = pd.read_parquet(perfect_row.processed / "counts.parquet").set_index("class_id")
    assert sorted(counts.index) == list(THING_IDS)
    assert counts["count"].sum() == len(seen) > 0
    for c in THING_IDS:
        assert counts.loc[c, "count"] == int((gt.loc[seen, "class_id"] == c).sum())


def test_fruits_the_detector_never_confirms_are_not_counted():
    # ten fruits confirmed in about 90 % of their frames, one in none of its 5, one in 1 of 12
    checked = {f: 10 for f in range(1, 11)} | {11: 5, 12: 12}
    confirmed = {f: 9 for f in range(1, 11)} | {11: 0, 12: 1}
    out = fruit_count.detector_support(checked, confirmed, alpha=0.01)
    assert [f for f, (_, u) in out.items() if u] == [11, 12]
    assert all(0 <= p <= 1 for p, _ in out.values()) and out[11][0] < 1e-3 < out[1][0]
    assert not any(u for _, u in fruit_count.detector_support(checked, confirmed, alpha=0.0).values())
    # a detector that confirms nearly everything: a fruit confirmed in 27 of 30 frames is still real
    checked = {f: 30 for f in range(1, 21)}
    confirmed = {f: 30 for f in range(1, 20)} | {20: 27}
    assert not any(u for _, u in fruit_count.detector_support(checked, confirmed, alpha=0.01).values())
    assert fruit_count.detector_support({}, {}, alpha=0.01) == {}
    # at the default level, a fruit seen in 2 frames and confirmed in neither is a phantom under a detector
    # that confirms 90 % of the fruits' frames; one confirmed in 2 of 4 frames is kept
    checked = {f: 10 for f in range(1, 11)} | {11: 2, 12: 4}
    confirmed = {f: 9 for f in range(1, 11)} | {11: 0, 12: 2}
    out = fruit_count.detector_support(checked, confirmed, alpha=fruit_count.Config().detector_alpha)
    assert [f for f, (_, u) in out.items() if u] == [11]


def test_a_fruit_without_a_fruit_shape_needs_the_detector_in_half_the_rows_share_of_frames():
    # twenty fruits confirmed in 85 % of their frames; fruit 21 is confirmed in 1 of its 3 frames, which a
    # real fruit is with a chance of about 0.06 (above the default level): kept with a fruit shape, not
    # counted without one (a leaf the render paints as fruit); fruit 22, shapeless, confirmed in 2 of 4 frames
    # (above half the rate) is kept
    checked = {f: 20 for f in range(1, 21)} | {21: 3, 22: 4}
    confirmed = {f: 17 for f in range(1, 21)} | {21: 1, 22: 2}
    alpha = fruit_count.Config().detector_alpha
    shaped = fruit_count.detector_support(checked, confirmed, alpha)
    assert shaped[21][0] > alpha and not any(u for _, u in shaped.values())
    out = fruit_count.detector_support(checked, confirmed, alpha, shapeless={21, 22, 5})
    assert [f for f, (_, u) in out.items() if u] == [21]
    assert all(out[f][0] == shaped[f][0] for f in checked)
    assert not any(u for _, u in fruit_count.detector_support(checked, confirmed, 0.0, shapeless={21}).values())


def test_counted_fruits_are_confirmed_by_the_detector(perfect_row):
    fruits = pd.read_parquet(perfect_row.processed / "fruits.parquet")
    counted = fruits[fruits.counted]
    assert len(counted) and (counted.n_confirmed_frames > 0).all()
    assert counted.detector_p.between(0, 1).all() and (counted.n_confirmed_frames <= counted.n_frames).all()


def test_surface_fits_recover_known_shapes():
    rng = np.random.default_rng(0)
    th, ph = rng.uniform(0.2, np.pi - 0.2, 800), rng.uniform(-np.pi / 2, np.pi / 2, 800)   # front half only
    a, c, centre = 0.035, 0.045, np.array([1.0, 0.6, 0.8])
    pts = centre + np.c_[a * np.sin(th) * np.sin(ph), -a * np.sin(th) * np.cos(ph), c * np.cos(th)]
    pts += rng.normal(0, 0.0005, pts.shape)
    got_c, dia, length = fruit_count.fit_spheroid(pts)
    assert abs(dia - 2 * a) < 0.002 and abs(length - 2 * c) < 0.004 and np.linalg.norm(got_c - centre) < 0.002
    sph = centre + a * np.c_[np.sin(th) * np.sin(ph), -np.sin(th) * np.cos(ph), np.cos(th)]
    got_c, r = fruit_count.fit_sphere(sph)
    assert abs(r - a) < 1e-4 and np.linalg.norm(got_c - centre) < 1e-4
    assert fruit_count.principal_extents(sph)[1] < 2 * a  # extents of a half-seen surface are biased low


def test_a_fit_that_extrapolates_a_whole_fruit_from_a_small_cap_is_rejected():
    # a 3 cm patch of a 10 cm-radius sphere: the fits find that sphere, a 20 cm 'fruit' from 3 cm of surface
    rng = np.random.default_rng(1)
    th, ph = rng.uniform(0, 0.15, 600), rng.uniform(0, 2 * np.pi, 600)
    pts = np.array([0.5, 0.4, 0.9]) + 0.1 * np.c_[np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)]
    loose = fruit_count.measure(pts, fruit_count.Config(max_fit_extent_ratio=100.0))
    assert loose["diameter_sphere_m"] == pytest.approx(0.2, abs=0.01)
    out = fruit_count.measure(pts, fruit_count.Config())
    assert out["diameter_sphere_m"] is None and out["diameter_spheroid_m"] is None
    assert out["diameter_m"] == out["diameter_pca_m"] < 0.04
    assert np.allclose([out["x_m"], out["y_m"], out["z_m"]], np.median(pts, 0), atol=0.005)


# -- outputs readable elsewhere --------------------------------------------------------------------------

@pytest.mark.parametrize("table", ["panoptic_frames", "fruit_slots", "fruits", "counts", "evaluation"])
def test_tables_are_readable_by_duckdb_and_polars_and_carry_units(perfect_row, table):
    duckdb = pytest.importorskip("duckdb")
    pl = pytest.importorskip("polars")
    path = perfect_row.processed / f"{table}.parquet"
    n = duckdb.sql(f"select count(*) from '{path}'").fetchall()[0][0]
    assert n == pl.read_parquet(path).height == len(pd.read_parquet(path)) > 0
    schema = pq.read_schema(path)
    if table == "fruits":
        assert schema.field("x_m").metadata[b"unit"] == b"m"
        assert schema.field("diameter_m").metadata[b"unit"] == b"m"


def test_fruit_map_ply_opens_in_open3d(perfect_row):
    o3d = pytest.importorskip("open3d")
    pcd = o3d.io.read_point_cloud(str(perfect_row.processed / "fruit_map" / "fruits.ply"))
    fruits = pd.read_parquet(perfect_row.processed / "fruits.parquet")
    pts = np.asarray(pcd.points)
    assert len(pts) == (fruits.n_points + fruits.n_outliers).sum() and pcd.has_colors()
    near = fruits[fruits.near_row]
    assert pts[:, 1].min() < near.y_m.max()


# -- evaluate --------------------------------------------------------------------------------------------

def test_evaluate_is_perfect_on_perfect_input(perfect_row):
    ev = evaluation(perfect_row)
    assert list(ev.columns) == ["scope", "metric", "value", "unit"]
    windows = sorted(s for s in ev.scope.unique() if s.startswith("window_"))
    assert windows == [f"window_{w:03d}" for w in sorted(perfect_row.windows.window_id.unique())]
    for w in windows:
        for k in ("pq", "sq", "rq", "miou", "id_consistency"):
            assert metric(ev, w, k) == pytest.approx(1.0), (w, k)
        assert metric(ev, w, "pq_detector") < 0.95 and 0 < metric(ev, w, "miou_detector") < 1
        assert metric(ev, w, "ate_refined_m") == pytest.approx(0, abs=1e-6)
        assert metric(ev, w, "ate_odometry_m") > 1e-4
        assert metric(ev, w, "psnr") == pytest.approx(25 + int(w[-3:]))
    for k in ("id_consistency", "fruit_recall", "fruit_precision", "class_accuracy"):
        assert metric(ev, "row", k) == pytest.approx(1.0), k
    # fusion voids slots under panoptic_fusion.min_slot_px pixels: a few 1-3 px fruit fragments are missed
    assert 0.99 < metric(ev, "row", "pq") < 1 and metric(ev, "row", "miou") > 0.99
    assert metric(ev, "row", "count_error_rel") == 0 and metric(ev, "row", "count_gt") > 0
    assert metric(ev, "row", "diameter_mae_m") < 0.012 and metric(ev, "row", "diameter_median_abs_err_m") < 0.01
    assert metric(ev, "row", "diameter_mae_m") < metric(ev, "row", "diameter_sphere_mae_m")
    units = ev.set_index("metric").unit
    assert units["psnr"].iloc[0] == "dB" and units["diameter_mae_m"] == "m" and units["pq"].iloc[0] == "fraction"


def split_and_drop(wid: int, fid: int, sem: np.ndarray, slots: np.ndarray):
    """Window 0: every fruit gets a new slot on every other frame. Window 1: its largest fruit is lost."""
    if wid == 0 and fid % 4 == 2:
        slots = np.where(slots > 0, slots + 500, 0)
    if wid == 1:
        ids, n = np.unique(slots[slots > 0], return_counts=True)
        if len(ids):
            lost = slots == ids[np.argmax(n)]
            sem, slots = np.where(lost, 1, sem), np.where(lost, 0, slots)
    return sem, slots


def test_evaluate_is_worse_on_split_slots_and_missed_fruits(make_row, perfect_row):
    row = make_row(hook=split_and_drop)
    run_stages(row)
    ev, good = evaluation(row), evaluation(perfect_row)
    assert metric(ev, "window_000", "id_consistency") < metric(good, "window_000", "id_consistency")
    assert metric(ev, "window_000", "pq") == pytest.approx(1.0)            # per-frame panoptics untouched
    assert metric(ev, "window_001", "pq") < metric(good, "window_001", "pq")
    assert metric(ev, "window_001", "miou") < 1.0
    assert metric(ev, "row", "id_consistency") < metric(good, "row", "id_consistency")


def test_evaluate_without_ground_truth_is_an_empty_table_with_a_note(perfect_row, tmp_path):
    frames = perfect_row.frames.assign(gt_semantic_path=None, gt_instance_path=None)
    (tmp_path / "raw").mkdir()
    ctx = StageContext(stage="evaluate", seq=SEQ, data_root=perfect_row.root, show_progress=False)
    out = evaluate.run({"raw": tmp_path / "raw", "frames": frames}, evaluate.Config(), ctx)
    assert out["evaluation"].empty and "no ground truth" in ctx.summary["notes"][0]


def test_pag_evaluate_runs_from_the_cli(perfect_row, capsys):
    args = ["evaluate", "--seq", SEQ, "--data-root", str(perfect_row.root), "--no-progress"]
    for kv in TINY:
        args += ["--set", kv]
    assert cli.main(args) == 0
    assert "evaluate:" in capsys.readouterr().err


def test_bad_config_is_rejected():
    with pytest.raises(ValueError, match="max_match_distance_m"):
        panoptic_fusion.Config(max_match_distance_m=0)
    with pytest.raises(ValueError, match="max_depth_m"):
        fruit_count.Config(max_depth_m=-1)


# -- report ----------------------------------------------------------------------------------------------

def test_report_is_one_self_contained_page_with_every_section(perfect_row):
    page = (perfect_row.processed / "report" / "report.html").read_text()
    for section in report.SECTIONS:
        assert f"<h2>{section}</h2>" in page, section
    n_windows = perfect_row.windows.window_id.nunique()
    assert page.count('src="data:image/png;base64,') == 5 * n_windows + 1   # 5 panels per window + the map
    assert "src=\"http" not in page and "src=\"/" not in page
    assert "nerf_fit:" in page and "fruit_green" in page and "pq_detector" in page


def test_without_any_panoptic_render_every_stage_still_writes_its_outputs(make_row):
    row = make_row()
    drop_renders(row, ("semantic", "instance"))                    # what nerf_fit writes without the panoptic phase
    run_stages(row)
    assert pd.read_parquet(row.processed / "panoptic_frames.parquet").empty
    assert pd.read_parquet(row.processed / "fruits.parquet").empty
    assert pd.read_parquet(row.processed / "counts.parquet")["count"].sum() == 0
    assert (row.processed / "fruit_map" / "fruits.ply").is_file()
    ev = evaluation(row)
    assert metric(ev, "window_000", "pq_detector") > 0 and metric(ev, "row", "count_pred") == 0
    assert "No fruit was fused" in (row.processed / "report" / "report.html").read_text()


def test_a_second_run_skips_the_four_stages(perfect_row):
    res = perfect_row.runner().run(["panoptic_fusion", "fruit_count", "evaluate", "report"])
    assert [r.status for r in res] == ["skipped"] * 4


def test_fruit_centres_are_moved_into_the_ground_truth_frame_through_a_frame_that_saw_them():
    ident = [0.0, 0.0, 0.0, 1.0]
    # odometry has drifted +0.05 m in x by frame 10 (none at frame 0); the ground truth has not
    frames = pd.DataFrame({"frame_id": [0, 10], "tx": [0.0, 1.05], "ty": 0.0, "tz": 0.0,
                           **dict(zip(["qx", "qy", "qz", "qw"], ident))})
    gt = pd.DataFrame({"frame_id": [0, 10], "tx": [0.0, 1.0], "ty": 0.0, "tz": 0.0,
                       **dict(zip(["qx", "qy", "qz", "qw"], ident))})
    fruits = pd.DataFrame({"x_m": [0.2, 1.25], "y_m": 0.5, "z_m": 0.1, "first_frame_id": [0, 9],
                           "last_frame_id": [1, 10]})
    moved = evaluate.to_ground_truth_frame(fruits, frames, gt)
    np.testing.assert_allclose(moved, [[0.2, 0.5, 0.1], [1.2, 0.5, 0.1]], atol=1e-9)
    np.testing.assert_allclose(evaluate.to_ground_truth_frame(fruits, frames, None), fruits[["x_m", "y_m", "z_m"]])


def test_the_fragment_rule_means_the_same_at_every_image_size():
    cfg = fruit_count.Config(min_count_frames=2, min_count_points=100)
    # a sliver of 150 px in each of 3 frames, its points capped per frame: at 320x180 a fruit, at 1280x720 the
    # same sliver covers 16 times the pixels and points, and is still a fruit
    small = sum(reference_pixels(150, 320 * 180) for _ in range(3))
    large = sum(reference_pixels(150 * 16, 1280 * 720) for _ in range(3))
    assert small == large == 450
    assert not fruit_count.is_fragment(3, 450, small, cfg) and not fruit_count.is_fragment(3, 1800, large, cfg)
    # a stray piece of 30 px per frame at 320x180 is a fragment; at 1280x720 (480 px per frame, 1440 points)
    # its points alone would pass, its reference pixels do not
    stray = sum(reference_pixels(480, 1280 * 720) for _ in range(3))
    assert stray == 90 and fruit_count.is_fragment(3, 1440, stray, cfg)
    assert fruit_count.is_fragment(3, 90, 90.0, cfg)
    # images smaller than 320x180 are not scaled up; too few frames or points stay fragments
    assert reference_pixels(100, 64 * 40) == 100
    assert fruit_count.is_fragment(1, 5000, 5000.0, cfg) and fruit_count.is_fragment(5, 60, 5000.0, cfg)


def test_a_lone_confirmed_fragment_is_counted_and_a_piece_next_to_a_counted_fruit_is_not():
    # fruit 1 counted at the origin; fragments the detector confirms in every frame: 2 and 5 stand alone, 3 lies
    # next to fruit 1 (a stray piece of it), 4 next to fragment 2 (two pieces of one fruit: counted once)
    fruits = pd.DataFrame({"fruit_id": [1, 2, 3, 4, 5], "counted": [True, False, False, False, False],
                           "n_points": [900, 150, 200, 60, 30],
                           "x_m": [0.0, 0.10, 0.03, 0.12, 0.30], "y_m": 0.0, "z_m": 0.5})
    assert fruit_count.lone_fragments(fruits, [2, 3, 4, 5], 0.06) == [2, 5]
    assert fruit_count.lone_fragments(fruits, [4, 2], 0.06) == [2]           # the one with more points wins
    assert fruit_count.lone_fragments(fruits, [2, 3, 4, 5], 0.0) == []       # 0 = off
    with pytest.raises(ValueError, match="lone_fragment_m"):
        fruit_count.Config(lone_fragment_m=-0.01)


def test_associate_compares_only_windows_whose_fruits_lie_within_the_gate(monkeypatch):
    cfg = panoptic_fusion.Config(max_match_distance_m=0.04, strong_match_distance_m=0.08)
    fruits = []
    for w in range(6):  # windows 0.5 m apart along the row; neighbours share a fruit at their meeting point
        for x in (0.5 * w, 0.5 * w + 0.25):
            c = np.array([x + 0.002 * w, 0.0, 1.0])
            fruits.append(panoptic_fusion.LocalFruit(w, len(fruits), 0, [(0, 0)], 50, 2, c, median=c))
        c = np.array([0.5 * w + 0.5 + 0.002 * w, 0.0, 1.0])  # the next window's first fruit, seen from here
        fruits.append(panoptic_fusion.LocalFruit(w, len(fruits), 0, [(0, 0)], 50, 2, c, median=c))
    compared = []
    real = panoptic_fusion.centre_distance
    monkeypatch.setattr(panoptic_fusion, "centre_distance",
                        lambda a, b: compared.append((a.window_id, b.window_id)) or real(a, b))
    groups = panoptic_fusion.associate(fruits, {}, cfg)
    assert set(compared) == {(w, w + 1) for w in range(5)}  # only neighbours are compared
    assert sorted(len(g) for g in groups) == [1] * 8 + [2] * 5  # and every shared fruit is matched


def test_a_fruit_wider_than_any_fruit_of_the_crop_is_not_counted():
    cfg = fruit_count.Config()
    rng = np.random.default_rng(3)

    def cap(centre, r, n=400):  # the camera-facing half of a sphere (the camera looks along +z)
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d[:, 2] = -np.abs(d[:, 2])
        return np.asarray(centre) + r * d

    one = fruit_count.measure(cap([0, 0, 1], 0.035), cfg)
    assert abs(one["diameter_m"] - 0.07) < 0.01 and not fruit_count.oversize(one["diameter_m"], cfg)
    # one id over two fruits side by side and the leaves between them: measured wider than any pepper
    two = fruit_count.measure(np.concatenate([cap([-0.06, 0, 1], 0.035), cap([0.06, 0, 1], 0.035),
                                              rng.uniform([-0.06, -0.03, 1.0], [0.06, 0.03, 1.02], (300, 3))]), cfg)
    assert two["diameter_m"] > cfg.max_count_diameter_m and fruit_count.oversize(two["diameter_m"], cfg)
    assert not fruit_count.oversize(None, cfg) and not fruit_count.oversize(float("nan"), cfg)
    assert not fruit_count.oversize(two["diameter_m"], fruit_count.Config(max_count_diameter_m=1e6))  # off
    with pytest.raises(ValueError, match="max_count_diameter_m"):
        fruit_count.Config(max_count_diameter_m=0)
