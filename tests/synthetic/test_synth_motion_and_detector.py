"""Odometry drift and the detector corruption of the synthetic row."""
import cv2
import numpy as np
import pytest

from synthetic import detector, trajectory
from synthetic.scene import BACKGROUND, GREEN, MIXED, PLANT, RED


def _odometry(drift=0.03, yaw=2.0, noise=0.0, seed=0):
    path = trajectory.BasePath.random(0.2, 0.4, 0.0, np.random.default_rng(seed))
    t = np.arange(0, 20.0, 0.02)
    x, y, th = path.xy_yaw(t)
    odo = trajectory.drifting_odometry(x, y, th, 0.4, trajectory.OdometryErrors(drift, yaw, noise),
                                       np.random.default_rng(seed + 1))
    return x, y, th, odo


def test_odometry_starts_true_and_drifts_with_distance():
    x, y, _, odo = _odometry(noise=0.002)
    err = np.hypot(odo[:, 0, 3] - x, odo[:, 1, 3] - y)
    assert err[0] == 0.0
    travelled = np.concatenate([[0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    assert travelled[-1] == pytest.approx(4.0, rel=0.05)
    at = [np.searchsorted(travelled, d) for d in (1.0, 2.0, 3.9)]
    assert err[at[0]] < err[at[1]] < err[at[2]]
    # 3 cm/m of translation drift plus the heading error: several cm after 4 m, well under a metre
    assert 0.1 < err[-1] < 0.6
    assert np.allclose(odo[:, 2, 3], 0.4)


def test_odometry_without_errors_is_the_truth():
    x, y, th, odo = _odometry(drift=0.0, yaw=0.0, noise=0.0)
    assert np.allclose(odo[:, 0, 3], x, atol=1e-9) and np.allclose(odo[:, 1, 3], y, atol=1e-9)
    assert np.allclose(np.arctan2(odo[:, 1, 0], odo[:, 0, 0]), th, atol=1e-9)


def test_camera_looks_left_at_the_row():
    t = trajectory.camera_extrinsic(0.35, 0.1)
    assert np.allclose(t[:3, 2], [0, 1, 0]) and np.allclose(t[:3, 1], [0, 0, -1]) and np.allclose(t[:3, 0], [1, 0, 0])
    assert np.allclose(t[:3, 3], [0, 0.1, 0.35])


def _frame():
    """Ground truth of a 60x80 frame: plant everywhere, three near fruits (two touching) and a far one."""
    h, w = 60, 80
    sem = np.full((h, w), PLANT, np.uint8)
    sem[:, 60:] = BACKGROUND
    inst = np.zeros((h, w), np.uint16)
    for fid, klass, (cy, cx) in ((1, GREEN, (15, 15)), (2, RED, (15, 31)), (3, MIXED, (45, 30))):
        m = np.zeros((h, w), np.uint8)
        cv2.circle(m, (cx, cy), 8, 1, -1)
        inst[m > 0] = fid
        sem[m > 0] = klass
    inst[40:44, 66:70] = 4
    sem[40:44, 66:70] = GREEN
    depth = np.full((h, w), 0.6, np.float32)
    depth[:, 60:] = 2.0
    sizes = detector.FruitSizes(np.array([0, 0.07, 0.07, 0.07, 0.07]), np.array([0, 0.08, 0.08, 0.08, 0.08]),
                                np.array([False, True, True, True, False]), 150.0, 150.0)
    return sem, inst, depth, sizes


def _noise(**kw):
    base = dict(miss_rate=0.0, false_pos_rate=0.0, boundary_px=0, merge_rate=0.0, class_confusion_rate=0.0,
                void_rate=0.0, min_area_px=5)
    return detector.DetectorNoise(**{**base, **kw})


def test_noise_free_detector_reproduces_ground_truth_up_to_ids():
    sem, inst, depth, sizes = _frame()
    det = detector.detect(sem, inst, depth, sizes, _noise(), np.random.default_rng(0))
    assert np.array_equal(det.semantic, sem)
    assert sorted(s for s, _, _ in det.segments) == [1, 2, 3, 4]
    for sid, klass, score in det.segments:
        gt_ids = np.unique(inst[det.instance == sid])
        assert len(gt_ids) == 1 and np.array_equal(det.instance == sid, inst == gt_ids[0])
        assert klass == np.bincount(sem[inst == gt_ids[0]]).argmax() and 0.75 <= score <= 0.99


def test_detector_ids_are_shuffled_per_frame():
    sem, inst, depth, sizes = _frame()
    ids = {tuple(np.unique(detector.detect(sem, inst, depth, sizes, _noise(), np.random.default_rng(s))
                           .instance[inst == 1])) for s in range(12)}
    assert len(ids) > 1


def test_missed_fruits_become_the_stuff_around_them():
    sem, inst, depth, sizes = _frame()
    det = detector.detect(sem, inst, depth, sizes, _noise(miss_rate=1.0), np.random.default_rng(0))
    assert det.segments == [] and det.instance.max() == 0
    assert np.all(det.semantic[(inst > 0) & (inst < 4)] == PLANT) and np.all(det.semantic[inst == 4] == BACKGROUND)


def test_merges_false_positives_confusions_and_boundaries():
    sem, inst, depth, sizes = _frame()
    merged = detector.detect(sem, inst, depth, sizes, _noise(merge_rate=1.0), np.random.default_rng(0))
    assert merged.stats["merged"] >= 1
    both = [s for s in np.unique(merged.instance[inst == 1]) if s and np.any(merged.instance[inst == 2] == s)]
    assert both and all(score <= 0.7 for sid, _, score in merged.segments if sid in both)
    fp = detector.detect(sem, inst, depth, sizes, _noise(false_pos_rate=5.0), np.random.default_rng(1))
    extra = [(sid, score) for sid, _, score in fp.segments if not np.any(inst[fp.instance == sid] > 0)]
    assert extra and all(0.3 <= s <= 0.7 for _, s in extra)
    conf = detector.detect(sem, inst, depth, sizes, _noise(class_confusion_rate=1.0), np.random.default_rng(2))
    for sid, klass, score in conf.segments:
        truth = int(np.bincount(sem[inst == np.unique(inst[conf.instance == sid])[0]]).argmax())
        assert klass in detector.NEIGHBOUR_CLASS[truth] and score <= 0.7
    b = 2
    jit = detector.detect(sem, inst, depth, sizes, _noise(boundary_px=b), np.random.default_rng(3))
    kernel = np.ones((2 * b + 1, 2 * b + 1), np.uint8)
    for fid in (1, 2, 3):
        m = (inst == fid).astype(np.uint8)
        sid = np.bincount(jit.instance[inst == fid]).argmax()
        d = (jit.instance == sid).astype(np.uint8)
        assert np.all(d <= cv2.dilate(m, kernel)) and np.all(cv2.erode(m, kernel) <= d + (jit.instance > 0))


def test_jitter_mask_moves_the_border_both_ways():
    m = np.zeros((50, 50), bool)
    m[10:40, 10:40] = True
    grow = detector.jitter_mask(m, 2, np.random.default_rng(0), bias=2.0)
    shrink = detector.jitter_mask(m, 2, np.random.default_rng(0), bias=-2.0)
    assert grow.sum() > m.sum() > shrink.sum()
    assert np.array_equal(detector.jitter_mask(m, 0, np.random.default_rng(0)), m)
