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

from nerf.geometry import pose_matrix, pose_txyzq
from nerf.surfaces import fruit_sphere, runs_by_key
from pipeline import cli
from pipeline.classes import THING_IDS
from pipeline.images import ImageError, read_label
from pipeline.stage import StageContext
from rowmap.detections import dropped_segments, fruit_segments
from rowmap.geometry import pixel_groups, sphere_behind, window_alignments, with_sensor_depth
from rowmap.renders import file_name
from rowmap.scoring import reference_pixels
from rowmap import ends
from rowmap.fusion import association
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
    xyz = ["x_m", "y_m", "z_m"]
    counts, worst = {}, {}
    for align in (True, False):
        row = make_row(name=f"align_{align}")
        shifted_window_poses(row, 1, t)
        run_stages(row, f"panoptic_fusion.align_windows={str(align).lower()}")
        fruits = pd.read_parquet(row.processed / "fruits.parquet")
        counts[align] = len(fruits)
        worst[align] = cKDTree(truth[xyz].to_numpy()).query(fruits[xyz].to_numpy())[0].max()
        if align:
            assert len(fruits) == len(truth)
            np.testing.assert_allclose(fruits[xyz], truth[xyz], atol=1e-6)
    # unaligned, the two windows' masks still make each fruit they both saw one fruit, but its model mixes the
    # two windows' frames: it lies cm off
    assert counts[False] == counts[True] and worst[False] > 0.03


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
    fruits = [association.LocalFruit(0, 1, 0, [(0, 0)], 50, 2, c),
              association.LocalFruit(0, 2, 0, [(0, 0)], 50, 2, c + [0.01, 0, 0]),
              association.LocalFruit(1, 5, 0, [(2, 0)], 50, 2, c + [0.005, 0, 0]),
              association.LocalFruit(2, 9, 0, [(4, 0)], 50, 2, c + [0.3, 0, 0])]
    groups = sorted(sorted(g) for g in association.associate(fruits, {}, cfg))
    assert groups == [[0, 2], [1], [3]]  # window 1's slot joins the nearer of window 0's two slots
    parts = association.split_frames({0: c, 1: c + 0.01, 5: c + [0.5, 0, 0], 6: None}, 0.08)
    assert parts == [[0, 1, 6], [5]]
    # a one-frame stray cluster is not a fruit of its own; two frames far away are
    far = c + [0.5, 0, 0]
    assert association.split_frames({0: c, 1: c + 0.01, 5: far, 6: None}, 0.08, min_frames=2) == [[0, 1, 5, 6]]
    assert association.split_frames({0: c, 1: c, 5: far, 7: far + 0.01}, 0.08, min_frames=2) == [[0, 1], [5, 7]]


def test_mask_overlaps_count_each_pair_of_codes_of_two_windows_once_in_either_order():
    rng = np.random.default_rng(3)
    m0, m1 = rng.integers(0, 4, (12, 10)).astype(np.int32), rng.integers(0, 3, (12, 10)).astype(np.int32)
    ov = association.MaskOverlaps({(0, 4): m0, (1, 4): m1, (0, 6): m0})   # frame 6: window 0 only
    assert ov.shared == {(0, 1): [4]}
    joint = ov.joint(0, 1, 4)
    assert {(x, y) for x, y, _ in joint} == {(x, y) for x in range(4) for y in range(3)} - {(0, 0)}
    for x, y, n in joint:
        assert n == np.count_nonzero((m0 == x) & (m1 == y))
    assert sorted(ov.joint(1, 0, 4)) == sorted((y, x, n) for x, y, n in joint)


def test_fusion_uses_mask_overlap_on_shared_frames():
    cfg = panoptic_fusion.Config()
    a = association.LocalFruit(0, 3, 0, [(4, 0)], 50, 2, np.zeros(3))
    b = association.LocalFruit(1, 8, 0, [(4, 0)], 50, 2, np.full(3, 0.005))
    m_a, m_b = np.zeros((6, 6), np.int32), np.zeros((6, 6), np.int32)
    m_a[:3, :3], m_b[:3, :3] = association.code(3, 0), association.code(8, 0)
    assert np.isfinite(association.pair_cost(a, b, association.MaskOverlaps({(0, 4): m_a, (1, 4): m_b}), cfg))
    m_b[:] = 0
    m_b[3:, 3:] = association.code(8, 0)  # close in 3D but disjoint masks on a frame both rendered
    assert association.pair_cost(a, b, association.MaskOverlaps({(0, 4): m_a, (1, 4): m_b}), cfg) == np.inf


def test_slots_on_shared_frames_match_as_far_apart_as_their_masks_agree_and_alone_only_within_the_gate():
    cfg = panoptic_fusion.Config(max_match_distance_m=0.04, min_mask_iou=0.3)
    a = association.LocalFruit(0, 3, 0, [(4, 0)], 50, 2, np.zeros(3))
    m_a, m_b = np.zeros((6, 6), np.int32), np.zeros((6, 6), np.int32)
    m_a[:3, :3], m_b[:3, :3] = association.code(3, 0), association.code(8, 0)   # the same mask in both windows
    m_b[:2, :2] = association.code(9, 0)                                           # but 4 of its 9 pixels
    overlaps = association.MaskOverlaps({(0, 4): m_a, (1, 4): m_b})

    def other(slot: int, x: float) -> association.LocalFruit:
        return association.LocalFruit(1, slot, 0, [(4, 0)], 50, 2, np.array([x, 0.0, 0.0]))

    # IoU 5/9: (1 - IoU) x (1 + distance / 4 cm), at most 1.5
    assert association.pair_cost(a, other(8, 0.03), overlaps, cfg) == pytest.approx(4 / 9 * (1 + 0.03 / 0.04))
    assert association.pair_cost(a, other(8, 0.09), overlaps, cfg) == pytest.approx(4 / 9 * (1 + 0.09 / 0.04))
    assert association.pair_cost(a, other(8, 0.1), overlaps, cfg) == np.inf      # 4/9 x 3.5 > 1.5
    piece = other(9, 0.0)                                                         # the 4 pixels: IoU 4/9
    assert association.pair_cost(a, piece, overlaps, cfg) == pytest.approx(5 / 9)
    strict = panoptic_fusion.Config(max_match_distance_m=0.04, min_mask_iou=0.5)
    assert association.pair_cost(a, piece, overlaps, strict) == np.inf           # under min_mask_iou
    m_b[:3, :3] = association.code(8, 0)                                          # the same mask again: IoU 1
    overlaps = association.MaskOverlaps({(0, 4): m_a, (1, 4): m_b})
    assert association.pair_cost(a, other(8, 0.15), overlaps, cfg) == 0.0
    assert association.pair_cost(a, other(8, 0.161), overlaps, cfg) == np.inf    # past MAX_PAIR_REACH gates
    alone = association.MaskOverlaps({(0, 4): m_a})                               # no shared frame: 0.5 + distance
    assert association.pair_cost(a, other(8, 0.04), alone, cfg) == pytest.approx(1.5)
    assert association.pair_cost(a, other(8, 0.041), alone, cfg) == np.inf


def test_a_fruit_one_window_placed_cm_off_is_one_fruit_where_both_windows_paint_its_pixels():
    cfg = panoptic_fusion.Config(max_match_distance_m=0.04)
    lf = association.LocalFruit
    a = lf(0, 1, 0, [(2, 0), (4, 0), (6, 0)], 900, 2, np.zeros(3))
    off = lf(1, 5, 0, [(4, 0), (6, 0)], 200, 2, np.array([0.05, 0.04, 0.0]))   # 6.4 cm off: seen at its border
    same = masks_of((4, 8), {(0, 4): [(1, slice(2, 6))], (1, 4): [(5, slice(2, 6))],
                             (0, 6): [(1, slice(1, 5))], (1, 6): [(5, slice(1, 5))]})
    assert sorted(sorted(g) for g in association.associate([a, off], same, cfg)) == [[0, 1]]
    apart = masks_of((4, 8), {(0, 4): [(1, slice(0, 3))], (1, 4): [(5, slice(4, 8))],
                              (0, 6): [(1, slice(0, 3))], (1, 6): [(5, slice(4, 8))]})
    alone = {(0, 4): same[(0, 4)], (0, 6): same[(0, 6)]}   # no frame of the pair rendered by both windows
    for masks in (apart, alone):
        assert sorted(sorted(g) for g in association.associate([a, off], masks, cfg)) == [[0], [1]]


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
    assert association.split_frames(centres, 0.08, min_frames=2) == [[(0, 0), (1, 0), (2, 0)],
                                                                        [(2, 1), (3, 0), (4, 0)]]
    with pytest.raises(ValueError, match="group_gap_m must be >= 0"):
        panoptic_fusion.Config(group_gap_m=-1.0)


def masks_of(shape: tuple[int, int], painted: dict[tuple[int, int], list[tuple[int, slice]]]) -> dict:
    """{(window, frame): slot-code image} with each listed (slot, column slice) painted over all rows."""
    out = {}
    for key, slots in painted.items():
        m = np.zeros(shape, np.int32)
        for slot, cols in slots:
            m[:, cols] = association.code(slot, 0)
        out[key] = m
    return out


def test_a_window_that_paints_a_fruit_with_two_slots_in_turn_gives_it_one_id():
    cfg = panoptic_fusion.Config()
    lf = association.LocalFruit
    c, x3 = np.zeros(3), np.array([0.03, 0.0, 0.0])
    a = lf(0, 1, 0, [(0, 0), (2, 0)], 50, 2, c)                 # window 0
    b1 = lf(1, 5, 0, [(2, 0), (4, 0)], 50, 2, c)                # window 1, then it loses the fruit ...
    b2 = lf(1, 6, 0, [(8, 0), (10, 0)], 50, 2, x3)              # ... and paints it with another slot
    w2 = lf(2, 9, 0, [(8, 0), (10, 0), (12, 0)], 50, 2, x3)     # window 2
    masks = masks_of((4, 8), {(0, 2): [(1, slice(0, 4))], (1, 2): [(5, slice(0, 4))],
                              (1, 8): [(6, slice(2, 6))], (2, 8): [(9, slice(2, 6))],
                              (1, 10): [(6, slice(2, 6))], (2, 10): [(9, slice(2, 6))]})
    # window 1 shows it on slot 6 where 2 sees it: slot 5 is matched as a pair without a frame both show
    overlaps = association.MaskOverlaps(masks)
    assert association.pair_cost(b1, w2, overlaps, cfg) == pytest.approx(0.5 + 0.03 / 0.04)
    assert association.pair_cost(b2, w2, overlaps, cfg) == 0.0
    groups = sorted(sorted(g) for g in association.associate([a, b1, b2, w2], masks, cfg))
    assert groups == [[0, 1, 2, 3]]


def test_a_slot_a_window_paints_a_fruit_with_only_after_their_shared_frames_joins_the_other_windows_fruit():
    # window 1 renders frames 4-10 and shares frame 4 with window 0, but paints the fruit (slot 5, 2 cm from
    # window 0's centre) only from frame 8; in frame 4 its slot 5 lies on another fruit, 30 cm away
    cfg = panoptic_fusion.Config()
    lf = association.LocalFruit
    a = lf(0, 1, 0, [(2, 0), (4, 0)], 400, 2, np.zeros(3))
    other = lf(1, 5, 1, [(4, 0), (6, 0)], 400, 2, np.array([0.3, 0.0, 0.0]))
    later = lf(1, 5, 0, [(8, 0), (10, 0)], 400, 2, np.array([0.02, 0.0, 0.0]))
    masks = masks_of((4, 8), {(0, 4): [(1, slice(0, 3))], (1, 4): [(5, slice(5, 8))]})
    overlaps = association.MaskOverlaps(masks)
    assert association.pair_cost(a, later, overlaps, cfg) == pytest.approx(0.5 + 0.02 / 0.04)
    assert association.pair_cost(a, other, overlaps, cfg) == np.inf
    assert sorted(sorted(g) for g in association.associate([a, other, later], masks, cfg)) == [[0, 2], [1]]
    # where window 1 paints that fruit's pixels with slot 5 in frame 4 and they miss window 0's, they stay apart
    later = lf(1, 5, 0, [(4, 0), (8, 0), (10, 0)], 400, 2, np.array([0.02, 0.0, 0.0]))
    masks[(1, 4)] = masks_of((4, 8), {(1, 4): [(5, slice(4, 8))]})[(1, 4)]
    assert association.pair_cost(a, later, association.MaskOverlaps(masks), cfg) == np.inf


def test_fruits_whose_masks_disagree_on_a_shared_frame_never_join_one_id_through_a_third_window():
    cfg = panoptic_fusion.Config()
    lf = association.LocalFruit
    c = np.zeros(3)
    main = lf(1, 2, 0, [(2, 0), (4, 0), (6, 0)], 900, 2, np.array([0.02, 0.0, 0.0]))  # window 1: the fruit
    piece = lf(1, 3, 0, [(4, 0), (6, 0)], 60, 2, c + 0.004)                            # ... and a stray piece
    w2 = lf(2, 7, 0, [(4, 0), (6, 0), (8, 0)], 900, 2, c)
    w3 = lf(3, 8, 0, [(10, 0), (12, 0)], 900, 2, c)      # shares no frame with window 1
    painted = [(2, slice(0, 4)), (3, slice(6, 8))]
    masks = masks_of((4, 8), {(1, 4): painted, (1, 6): painted,
                              (2, 4): [(7, slice(0, 2))], (2, 6): [(7, slice(0, 2))]})
    overlaps = association.MaskOverlaps(masks)
    assert association.pair_cost(piece, w3, overlaps, cfg) < association.pair_cost(main, w2, overlaps, cfg)
    groups = sorted(sorted(g) for g in association.associate([main, piece, w2, w3], masks, cfg))
    assert groups == [[0, 2, 3], [1]]   # the piece's mask misses window 2's fruit, so it stays apart


def test_a_piece_a_window_painted_beside_a_fruits_slot_joins_that_fruit_where_the_other_window_holds_it():
    cfg = panoptic_fusion.Config()
    lf = association.LocalFruit
    main = lf(1, 2, 0, [(4, 0), (6, 0)], 400, 2, np.zeros(3))
    piece = lf(1, 3, 0, [(4, 0), (6, 0)], 100, 2, np.array([0.01, 0.0, 0.0]))   # same frames: a second slot
    other = lf(2, 7, 0, [(4, 0), (6, 0), (8, 0)], 700, 2, np.array([0.005, 0.0, 0.0]))
    for reach, joins in ((7, True), (4, False)):   # window 2's mask of the fruit covers the piece, or not
        masks = masks_of((4, 8), {(1, 4): [(2, slice(0, 4)), (3, slice(4, 6))],
                                  (1, 6): [(2, slice(0, 4)), (3, slice(4, 6))],
                                  (2, 4): [(7, slice(0, reach))], (2, 6): [(7, slice(0, reach))]})
        groups = sorted(sorted(g) for g in association.associate([main, piece, other], masks, cfg))
        assert groups == ([[0, 1, 2]] if joins else [[0, 2], [1]])
    far = lf(1, 3, 0, [(4, 0), (6, 0)], 100, 2, np.array([0.06, 0.0, 0.0]))   # beyond max_match_distance_m
    masks = masks_of((4, 8), {(1, 4): [(2, slice(0, 4)), (3, slice(4, 6))], (2, 4): [(7, slice(0, 7))]})
    groups = sorted(sorted(g) for g in association.associate([main, far, other], masks, cfg))
    assert groups == [[0, 2], [1]]
    # the join's gate is on the sphere centres: a piece whose points' median lies by the fruit's but whose
    # sphere sits 6 cm off stays apart, though a pair of windows' slots may match on their medians
    main.median, other.median = np.zeros(3), np.array([0.005, 0.0, 0.0])
    far.median = np.array([0.01, 0.0, 0.0])
    assert association.centre_distance(far, other) == pytest.approx(0.005)
    groups = sorted(sorted(g) for g in association.associate([main, far, other], masks, cfg))
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
    row.runner().run(["panoptic_fusion"], force=True)
    pf = pd.read_parquet(row.processed / "panoptic_frames.parquet").set_index("frame_id")
    fused = read_label(row.root / pf.loc[fid, "instance_path"], "fused")
    own = np.bincount(fused[(g_inst == a) & ~stolen]).argmax()
    assert (fused[stolen] == own).mean() >= 0.9


def test_a_frame_the_nearest_window_rendered_without_its_fruits_gets_them_from_the_fruit_models(
        make_row, tiny_row_upstream):
    """The fused frame is the nearest window's render; the fruits it failed to paint come back where the detector
    shows them, through the models fitted to the other windows' views."""
    windows = pd.read_parquet(tiny_row_upstream / "interim" / SEQ / "windows.parquet")
    val = windows[windows.split == "val"].assign(d=lambda t: t.offset.abs()).sort_values(["frame_id", "d", "window_id"])
    shared = val.groupby("frame_id").window_id.nunique().loc[lambda n: n > 1].index
    nearest = {int(f): int(val[val.frame_id == f].window_id.iloc[0]) for f in shared}
    assert nearest, "the tiny row's windows share no rendered frame"

    def lose_fruits(wid: int, fid: int, sem: np.ndarray, slots: np.ndarray):
        if nearest.get(fid) == wid:
            sem, slots = np.where(slots > 0, 1, sem), np.zeros_like(slots)
        return sem, slots

    whole = make_row(name="whole")
    whole.runner().run(["panoptic_fusion"], force=True)
    row = make_row(hook=lose_fruits)
    row.runner().run(["panoptic_fusion"], force=True)
    pf = pd.read_parquet(row.processed / "panoptic_frames.parquet").set_index("frame_id")
    pf_whole = pd.read_parquet(whole.processed / "panoptic_frames.parquet").set_index("frame_id")
    found = n_fruit_px = 0
    for f in nearest:
        assert pf.loc[f, "window_id"] == nearest[f]
        fused = read_label(row.root / pf.loc[f, "instance_path"], "fused")
        expected = read_label(whole.root / pf_whole.loc[f, "instance_path"], "fused")
        found += int(((fused > 0) & (expected > 0)).sum())
        n_fruit_px += int((expected > 0).sum())
    assert n_fruit_px > 0 and found >= 0.6 * n_fruit_px   # measured 0.75: the detector's segments are smaller


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
        row.runner(f"fruit_count.surface_depth={which}").run(
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
    # fusion voids slots of a few pixels, and gives a fruit detector pixels just past its painted outline (a
    # segment painted mostly as background says some fruit is there: leaf pixels on a fruit's surface inside it
    # can go to the fruit; .988 before that, .984 with it)
    assert 0.98 < metric(ev, "row", "pq") < 1 and metric(ev, "row", "miou") > 0.99
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
    # the fusion gives window 0's two slots of each fruit one row id; the lost fruit's pixels still cost PQ
    assert metric(ev, "row", "id_consistency") == metric(good, "row", "id_consistency") == 1.0
    assert metric(ev, "row", "pq") < metric(good, "row", "pq")


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


def front_cap(rng, centre, r: float, n: int = 400) -> np.ndarray:
    """Points on the camera-facing half of a sphere (the camera looks along +z)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = -np.abs(d[:, 2])
    return np.asarray(centre, np.float64) + r * d


def end_track(rng, centre, frames: list[int], r: float = 0.035, points: np.ndarray | None = None) -> ends.Track:
    """A detector track seen in `frames`, each segment the front cap of a fruit at `centre` (or `points`)."""
    t = ends.Track()
    for f in frames:
        pts = front_cap(rng, centre, r) if points is None else points
        ends.extend(t, f, (2, pts, pts[:, 2], 300.0, np.median(pts, 0)))
    return t


def test_a_fruit_the_detector_alone_tracks_at_a_recording_end_is_counted_unless_a_fruit_explains_it():
    rng = np.random.default_rng(5)
    cfg = fruit_count.Config()
    # fruit 1 counted at the origin (7 cm wide); fruit 2 a fragment, not counted
    fruits = pd.DataFrame({"fruit_id": [1, 2], "counted": [True, False], "diameter_m": [0.07, 0.06],
                           "x_m": [0.0, 0.20], "y_m": 0.0, "z_m": 1.0})
    alone = end_track(rng, [0.12, 0.0, 1.0], [117, 118, 119])
    at_fruit = end_track(rng, [0.01, 0.0, 1.0], [117, 118, 119])         # fruit 1 itself, tracked again
    once = end_track(rng, [-0.15, 0.0, 1.0], [119])                       # one frame: a stray segment
    glimpse = end_track(rng, [-0.3, 0.1, 1.0], [118, 119])                # in view for two frames only
    by_fragment = end_track(rng, [0.20, 0.0, 1.0], [0, 1, 2])             # the fragment's fruit, seen enough
    # a fruit at the image border: a cap of 25 degrees around the ray, too shallow for any surface fit
    d = front_cap(rng, [0.0, 0.0, 0.0], 1.0, n=1000)
    cap = [-0.3, 0.0, 1.0] + 0.035 * d[d[:, 2] < -np.cos(np.radians(25))]
    assert not fruit_count.has_shape(fruit_count.measure(cap, cfg))
    shallow = end_track(rng, None, [0, 1, 2], points=cap)
    far = end_track(rng, [0.4, 0.0, 2.0], [0, 1, 2])                      # the far row
    picked = fruit_count.end_fruits([alone, at_fruit, once, glimpse, by_fragment, shallow, far], fruits, cfg)
    assert sorted(map(id, (t for t, _ in picked))) == sorted(map(id, [alone, by_fragment, shallow]))
    m = dict((id(t), m) for t, m in picked)[id(alone)]
    assert np.linalg.norm([m["x_m"] - 0.12, m["y_m"], m["z_m"] - 1.0]) < 0.01 and abs(m["diameter_m"] - 0.07) < 0.01
    # two tracks of one fruit count once; a track overlapping a counted fruit's sphere does not count, however
    # far apart the centres (a segment merging two fruits measures wide and lies between them)
    twice = fruit_count.end_fruits([alone, end_track(rng, [0.125, 0.0, 1.0], [118, 119])], fruits, cfg)
    assert len(twice) == 1
    wide = end_track(rng, [0.08, 0.0, 1.03], [117, 118, 119], r=0.06)   # 8.5 cm from fruit 1, 12 cm wide
    assert fruit_count.end_fruits([wide], fruits, cfg) == []
    assert fruit_count.end_fruits([alone], fruits, fruit_count.Config(end_tracks=False)) == []
    assert fruit_count.end_fruits([alone], fruits, fruit_count.Config(lone_fragment_m=0.0)) == []


def test_end_tracks_link_a_fruits_segments_frame_to_frame_in_the_frames_fused_frames_cannot_cover():
    rng = np.random.default_rng(6)
    assert ends.end_zones([1, 5, 9, 13], list(range(16))) == [0, 1, 2, 3, 4, 10, 11, 12, 13, 14, 15]
    assert ends.end_zones([3], list(range(5))) == list(range(5))
    # a window that failed leaves a gap in the fused frames: its frames, and the runs' ends beside it, are zones
    fused = [*range(0, 40, 4), *range(80, 120, 4)]
    assert ends.end_zones(fused, list(range(120))) == [*range(0, 4), *range(33, 84), *range(113, 120)]
    # a frame between fused frames is placed through the nearest one: the row frame is the odometry's moved
    odometry = {f: pose_matrix(np.array([0.01 * f, 0, 0, 0, 0, 0, 1.0])) for f in range(10)}
    shift = pose_matrix(np.array([0.2, -0.1, 0.0, 0.0, 0.0, np.sin(0.05), np.cos(0.05)]))
    fused = {f: shift @ odometry[f] for f in (2, 6)}
    assert np.allclose(ends.row_pose(9, fused, odometry), shift @ odometry[9])
    # two fruits 6 cm apart, each seen from frame 0 on, one missed by the detector in frame 2; a third fruit
    # enters in frame 3; segments under min_points points are left out
    a, b, c = [0.0, 0.0, 1.0], [0.06, 0.0, 1.0], [0.3, 0.0, 1.0]

    def seg(centre, n=300):
        pts = front_cap(rng, centre, 0.03, n)
        return (2, pts, pts[:, 2], float(n))

    views = [(0, [seg(a), seg(b)]), (1, [seg(b), seg(a), seg(c, n=5)]), (2, [seg(a)]), (3, [seg(a), seg(b), seg(c)])]
    tracks = ends.link(views, link_m=0.03, min_points=20)
    assert sorted(t.frames for t in tracks) == [[0, 1, 2, 3], [0, 1, 3], [3]]
    for t in tracks:
        assert len({tuple(np.round(np.median(p, 0), 1)) for p in t.points}) == 1   # one fruit per track
    # a segment farther than link_m from every track, or more than MAX_GAP_FRAMES after it, starts a track
    late = [(0, [seg(a)]), (0 + ends.MAX_GAP_FRAMES + 1, [seg(a)])]
    assert [t.frames for t in ends.link(late, 0.03, 20)] == [[0], [ends.MAX_GAP_FRAMES + 1]]


def test_fruits_seen_only_outside_the_fused_frames_are_counted_from_the_detector_once(make_row):
    # only the first two fused frames are kept, as if the rest of the recording were its end: the fruits seen
    # only later come back from the detector's tracks, placed where the ground truth has them, and no fruit the
    # fused frames hold is counted twice
    row = make_row()
    row.runner().run(["panoptic_fusion"], force=True)
    pf = pd.read_parquet(row.processed / "panoptic_frames.parquet")
    pf[pf.frame_id.isin(sorted(pf.frame_id)[:2])].to_parquet(row.processed / "panoptic_frames.parquet")
    counted = {}
    for on in (True, False):
        row.runner(f"fruit_count.end_tracks={str(on).lower()}").run(["fruit_count"], force=True)
        fruits = pd.read_parquet(row.processed / "fruits.parquet")
        counted[on] = fruits[fruits.counted.astype(bool)]
    ends_ = counted[True][counted[True].end_track_frames.notna()]
    assert len(ends_) > 0 and len(counted[True]) == len(counted[False]) + len(ends_)
    assert (ends_.n_frames == 0).all() and (ends_.end_track_frames >= 2).all()
    gt = row.gt_fruits[row.gt_fruits.near_row.astype(bool)][["x_m", "y_m", "z_m"]].to_numpy()
    xyz = counted[True][["x_m", "y_m", "z_m"]].to_numpy()
    d_gt = np.linalg.norm(xyz[:, None] - gt[None], axis=2)
    assert (np.linalg.norm(ends_[["x_m", "y_m", "z_m"]].to_numpy()[:, None] - gt[None], axis=2).min(1) < 0.02).all()
    assert len(set(d_gt.argmin(1))) == len(xyz)                    # no real fruit counted twice


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


def test_the_structure_holds_the_rows_stuff_surfaces_and_leaves_the_fruits_out(perfect_row):
    """structure.parquet (what `pag track` registers dates on): the plants' stems and leaves (this row's
    camera sees no floor within fruit_count.max_depth_m), no fruit surface."""
    s = pd.read_parquet(perfect_row.processed / "structure.parquet")
    assert len(s) > 500 and set(s.class_id) <= {0, 1} and (s.n_points >= 1).all()
    xyz = s[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
    cams = pd.read_parquet(perfect_row.processed / "panoptic_frames.parquet")[["tx", "ty", "tz"]].to_numpy()
    assert np.linalg.norm(xyz[:, None] - cams[None], axis=2).min(1).max() < 1.5      # seen within max_depth_m
    gt = perfect_row.gt_fruits
    d = np.linalg.norm(xyz[:, None] - gt[["x_m", "y_m", "z_m"]].to_numpy()[None], axis=2) / gt.diameter_m.to_numpy()
    inside = (d < 0.45).any(1)                                             # within a fruit's surface
    assert inside.mean() < 0.005, inside.sum()


def test_a_counted_fruit_lying_on_a_counted_fruit_with_more_points_is_one_fruit_under_two_ids():
    # 1 and 2 lie 2 mm apart (one fruit a window painted with two slots), 3 touches 1 (two fruits, 6 cm apart),
    # 4 lies on 1 but is not counted, 5 and 6 are a second pair with equal points (the lower id is kept)
    fruits = pd.DataFrame({"fruit_id": [1, 2, 3, 4, 5, 6], "counted": [True, True, True, False, True, True],
                           "n_points": [300, 900, 500, 50, 400, 400],
                           "x_m": [0.0, 0.002, 0.06, 0.001, 0.5, 0.51], "y_m": 0.0, "z_m": 0.5})
    assert fruit_count.duplicates(fruits, 0.03) == [1, 6]
    assert fruit_count.duplicates(fruits, 0.0) == []                        # 0 = off
    assert fruit_count.duplicates(fruits, 0.07) == [1, 3, 6]               # past two radii it merges neighbours
    with pytest.raises(ValueError, match="duplicate_within_m"):
        fruit_count.Config(duplicate_within_m=-0.01)
