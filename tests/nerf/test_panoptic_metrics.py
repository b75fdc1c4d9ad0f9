import numpy as np
import pytest
import torch
from torchmetrics.classification import MulticlassJaccardIndex
from torchmetrics.detection import PanopticQuality

from nerf.panoptic_metrics import (ConfusionAccumulator, PanopticAccumulator, dominant_ids, id_consistency,
                                  id_failures)

# torchmetrics' documented PanopticQuality example: PQ = 0.5463.
PRED = np.array([[[6, 0], [0, 0], [6, 0], [6, 0]], [[0, 0], [0, 0], [6, 0], [0, 1]],
                 [[0, 0], [0, 0], [6, 0], [0, 1]], [[0, 0], [7, 0], [6, 0], [1, 0]],
                 [[0, 0], [7, 0], [7, 0], [7, 0]]])
TARGET = np.array([[[6, 0], [0, 1], [6, 0], [0, 1]], [[0, 1], [0, 1], [6, 0], [0, 1]],
                   [[0, 1], [0, 1], [6, 0], [1, 0]], [[0, 1], [7, 0], [1, 0], [1, 0]],
                   [[0, 1], [7, 0], [7, 0], [7, 0]]])


def ours(preds, targets, things, stuff):
    acc = PanopticAccumulator(set(things), set(stuff))
    for p, t in zip(preds, targets):
        acc.update(p[..., 0], p[..., 1], t[..., 0], t[..., 1])
    return acc.compute()


def theirs(preds, targets, things, stuff):
    m = PanopticQuality(things=set(things), stuffs=set(stuff), allow_unknown_preds_category=True,
                        return_sq_and_rq=True)
    return m(torch.as_tensor(np.stack(preds)), torch.as_tensor(np.stack(targets))).double().numpy()


def test_documented_example():
    r = ours([PRED], [TARGET], {0, 1}, {6, 7})
    assert r["pq"] == pytest.approx(0.5463, abs=5e-5)
    pq, sq, rq = theirs([PRED], [TARGET], {0, 1}, {6, 7})
    assert (r["pq"], r["sq"], r["rq"]) == pytest.approx((pq, sq, rq), abs=1e-6)


def test_hand_made_cases():
    gt = np.zeros((4, 6, 2), np.int64)
    gt[:, :3] = [2, 1]                       # fruit 1 (class 2) on the left half, background right
    perfect = gt.copy()
    assert ours([perfect], [gt], {2}, {0})["pq"] == 1.0
    shifted = gt.copy()
    shifted[:, 2] = [0, 0]                   # prediction covers 8 of 12 fruit pixels: IoU 2/3
    r = ours([shifted], [gt], {2}, {0})
    assert r["pq_2"] == pytest.approx(2 / 3)
    wrong_class = gt.copy()
    wrong_class[:, :3] = [3, 1]              # right mask, wrong class: one FN for 2, one FP for 3
    r = ours([wrong_class], [gt], {2, 3}, {0})
    assert r["pq_2"] == 0 and r["pq_3"] == 0


def test_void_pixels_are_ignored_like_the_reference():
    gt = np.zeros((4, 6, 2), np.int64)
    gt[:, :3] = [2, 1]
    gt[:, 5] = [255, 0]                      # void column
    pred = gt.copy()
    pred[:, 5] = [2, 7]                      # a predicted fruit entirely on void: not a false positive
    r = ours([pred], [gt], {2}, {0})
    assert r["pq"] == 1.0


@pytest.mark.parametrize("seed", range(6))
def test_random_cases_agree_with_torchmetrics(seed):
    rng = np.random.default_rng(seed)
    preds, targets = [], []
    for _ in range(3):
        t = np.zeros((12, 16, 2), np.int64)
        p = np.zeros((12, 16, 2), np.int64)
        t[..., 0] = rng.integers(0, 2, size=(12, 16))
        p[..., 0] = t[..., 0]
        for k in range(1, 5):                # blocky fruits, predictions perturbed
            y, x = rng.integers(0, 9), rng.integers(0, 12)
            c = rng.integers(2, 4)
            t[y:y + 4, x:x + 4] = [c, k]
            dy, dx = rng.integers(-1, 2, size=2)
            if rng.random() < 0.8:
                p[max(0, y + dy):y + dy + 4, max(0, x + dx):x + dx + 4] = [c if rng.random() < 0.9 else 5 - c, 10 + k]
        preds.append(p)
        targets.append(t)
    r = ours(preds, targets, {2, 3}, {0, 1})
    pq, sq, rq = theirs(preds, targets, {2, 3}, {0, 1})
    assert (r["pq"], r["sq"], r["rq"]) == pytest.approx((pq, sq, rq), abs=1e-6)


def test_miou_matches_torchmetrics_and_ignores_void():
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 4, size=(20, 20))
    pred = np.where(rng.random((20, 20)) < 0.7, gt, rng.integers(0, 4, size=(20, 20)))
    gt_void = gt.copy()
    gt_void[:3] = 255
    acc = ConfusionAccumulator(4)
    acc.update(pred, gt_void)
    ref = MulticlassJaccardIndex(num_classes=4, ignore_index=255, average="macro")
    assert acc.miou() == pytest.approx(float(ref(torch.as_tensor(pred), torch.as_tensor(gt_void))), abs=1e-6)


def test_id_consistency_requires_one_unique_id_per_fruit():
    gt = np.array([[1, 1, 2, 2, 0]])
    frames = [
        dominant_ids(gt, np.array([[5, 5, 6, 6, 0]]), [1, 2]),
        dominant_ids(gt, np.array([[5, 5, 6, 6, 0]]), [1, 2]),
        dominant_ids(gt, np.array([[5, 5, 5, 5, 0]]), [1, 2]),  # fruit 2 takes fruit 1's id here
    ]
    share, n = id_consistency(frames)
    assert n == 2 and share == 0.0
    share, n = id_consistency(frames[:2], min_frames=2)
    assert share == 1.0
    assert id_consistency(frames[:2], min_frames=3) == (pytest.approx(float("nan"), nan_ok=True), 0)


def test_id_failures_name_why_each_fruit_fails():
    # fruit 1: id 5 in every frame but one, where fruit 2 paints it with 6 (fails on one frame, shares 6)
    # fruit 2: id 6 throughout (fails: fruit 1 carries 6 once); fruit 3: unlabelled in one frame, else 7
    # fruit 4: two ids, 8 and 9, half and half (split); fruit 5: 10 throughout (passes)
    frames = [{1: 5, 2: 6, 3: 7, 4: 8, 5: 10}, {1: 5, 2: 6, 3: 0, 4: 8, 5: 10},
              {1: 6, 2: 6, 3: 7, 4: 9, 5: 10}, {1: 5, 2: 6, 3: 7, 4: 9, 5: 10}]
    assert id_consistency(frames) == (pytest.approx(0.2), 5)
    assert id_failures(frames) == {"unlabelled": 1, "split": 2, "shared": 2, "one_frame": 2}
    assert id_failures(frames, min_frames=5) == {"unlabelled": 0, "split": 0, "shared": 0, "one_frame": 0}


def test_fruits_below_the_visible_size_are_not_scored_in_that_frame():
    gt = np.array([[1, 1, 1, 2, 0]])
    pred = np.array([[5, 5, 5, 0, 0]])                # fruit 2 shows one pixel and gets no id
    assert dominant_ids(gt, pred, [1, 2]) == {1: 5, 2: 0}
    assert dominant_ids(gt, pred, [1, 2], min_px=2) == {1: 5}
