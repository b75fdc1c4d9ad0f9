"""The panoptic phase on a fitted tiny window (nerf/panoptic/train.py, render.py, result.py)."""
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from scene_fixture import tiny_window  # noqa: E402

from nerf.config import PanopticConfig, preset  # noqa: E402
from nerf.panoptic.labels import WindowLabels  # noqa: E402
from nerf.panoptic.render import render_panoptic  # noqa: E402
from nerf.panoptic.result import load_panoptic  # noqa: E402
from nerf.panoptic.train import fit_panoptic  # noqa: E402
from nerf.panoptic_metrics import dominant_ids  # noqa: E402
from nerf.trainer import fit_window  # noqa: E402

COLOUR = dict(steps=120, rays_per_step=512, occupancy_every=30, refine_poses=False, n_levels=8, log2_capacity=14)
FAST = PanopticConfig(steps=300, frames_per_step=2, rays_per_frame=256, min_segment_px=3)


def detector_like(sem: np.ndarray, inst: np.ndarray, seed: int = 0) -> WindowLabels:
    """Ground truth with per-frame shuffled instance ids (what a still-image detector gives)."""
    rng = np.random.default_rng(seed)
    out = np.zeros_like(inst)
    for i in range(len(inst)):
        ids = np.unique(inst[i][inst[i] > 0])
        new = rng.permutation(len(ids)) + 1
        for a, b in zip(ids, new):
            out[i][inst[i] == a] = b
    return WindowLabels(sem.astype(np.uint8), out)


@pytest.fixture(scope="module")
def fitted():
    data, sem, inst = tiny_window(n=8, w=80, h=45, labels=True)
    res = fit_window(data, preset("cpu", **COLOUR))
    return data, sem, inst, res.model


def test_panoptic_phase_renders_the_classes_and_one_id_per_fruit(fitted):
    data, sem, inst, model = fitted
    labels = detector_like(sem, inst)
    pres = fit_panoptic(model, labels, data.is_train, data.depths, FAST)
    assert pres.assignments > 0 and pres.history[-1]["loss"] < pres.history[0]["loss"]
    val = np.flatnonzero(~data.is_train)
    correct = total = 0
    per_frame = []
    for i in val:
        r = render_panoptic(model, pres, int(i))
        assert r["semantic"].shape == sem[i].shape and r["instance"].dtype == np.int32
        assert set(np.unique(r["instance"][np.isin(r["semantic"], [0, 1])])) <= {0}  # stuff carries no id
        fruit = r["fruit"]   # the thing classes' probability: high where a fruit is labelled, low on stuff
        assert fruit.shape == sem[i].shape and 0 <= fruit.min() and fruit.max() <= 1
        assert np.median(fruit[r["instance"] > 0]) > 0.5 > np.median(fruit[np.isin(r["semantic"], [0, 1])])
        correct += int((r["semantic"] == sem[i]).sum())
        total += sem[i].size
        big = [f for f, n in zip(*np.unique(inst[i], return_counts=True)) if f > 0 and n >= 30]
        per_frame.append(dominant_ids(inst[i], r["instance"], big))
    majority = max(np.mean(sem[val] == c) for c in np.unique(sem))
    assert correct / total > max(0.7, majority + 0.1)
    # a fruit seen large enough in several validation frames keeps one id in all of them
    seen: dict[int, set[int]] = {}
    for frame in per_frame:
        for f, p in frame.items():
            seen.setdefault(f, set()).add(p)
    multi = [f for f in seen if sum(f in fr for fr in per_frame) >= 2]
    assert multi, "the fixture should show some fruit in several validation frames"
    consistent = [f for f in multi if len(seen[f]) == 1 and 0 not in seen[f]]
    assert len(consistent) >= 0.6 * len(multi)


def test_checkpoint_round_trip_renders_the_same(fitted):
    data, sem, inst, model = fitted
    cfg = PanopticConfig(steps=10, frames_per_step=2, rays_per_frame=64)
    pres = fit_panoptic(model, detector_like(sem, inst), data.is_train, data.depths, cfg)
    again = load_panoptic(pres.state(), model)
    a, b = render_panoptic(model, pres, 1), render_panoptic(model, again, 1)
    assert np.array_equal(a["semantic"], b["semantic"]) and np.array_equal(a["instance"], b["instance"])


def test_chunked_render_labels_equal_the_whole_image_distributions_labelled(fitted):
    from nerf.panoptic.post import panoptic_labels
    from nerf.panoptic.samples import ray_probs, weighted_samples
    from nerf.render import pixel_rays

    data, sem, inst, model = fitted
    pres = fit_panoptic(model, detector_like(sem, inst), data.is_train, data.depths,
                        PanopticConfig(steps=40, frames_per_step=2, rays_per_frame=128))
    w, h = model.wh
    c2w, k, u, v = model.image_pixels(1, None, None)
    with torch.no_grad():
        ks = weighted_samples(model, *pixel_rays(k.expand(len(u), 4), c2w.expand(len(u), 4, 4), u, v),
                              pres.cfg.min_weight)
        p_sem, p_inst = ray_probs(pres.field, ks)
    sem_ref, inst_ref = panoptic_labels(p_sem.reshape(h, w, -1).numpy(), p_inst.reshape(h, w, -1).numpy(), pres.cfg,
                                        ks.depth.reshape(h, w).numpy())
    r = render_panoptic(model, pres, 1, chunk=500)          # 8 chunks, each reduced to its best slots
    assert (inst_ref > 0).any()
    assert np.array_equal(r["semantic"], sem_ref) and np.array_equal(r["instance"], inst_ref)


def test_all_void_labels_train_nothing_and_still_render(fitted):
    data, sem, _, model = fitted
    void = WindowLabels(np.full(sem.shape, 255, np.uint8), np.zeros(sem.shape, np.int32))
    pres = fit_panoptic(model, void, data.is_train, data.depths, PanopticConfig(steps=5))
    assert pres.steps == 0 and pres.assignments == 0
    r = render_panoptic(model, pres, 0)
    assert np.isfinite(r["rgb"].numpy()).all() and r["semantic"].max() < 5


def test_window_without_fruit_detections_skips_the_instance_part(fitted):
    data, sem, inst, model = fitted
    plant = np.where(np.isin(sem, [2, 3, 4]), 1, sem).astype(np.uint8)   # the detector saw no fruit at all
    labels = WindowLabels(plant, np.zeros_like(inst))
    cfg = PanopticConfig(steps=40, stuff_only_steps=10, frames_per_step=2, rays_per_frame=64)
    pres = fit_panoptic(model, labels, data.is_train, data.depths, cfg)
    assert pres.instances_skipped and pres.steps == 10 and pres.assignments == 0 and not pres.cfg.instances
    assert pres.params < fit_panoptic(model, detector_like(sem, inst), data.is_train, data.depths,
                                      PanopticConfig(steps=1)).params            # instance head not counted
    r = render_panoptic(model, load_panoptic(pres.state(), model), 1)
    assert (r["instance"] == 0).all()


def test_confidence_is_the_segment_score_one_for_stuff_zero_for_void():
    sem = np.array([[[2, 2, 1], [255, 1, 2]], [[1, 1, 1], [2, 255, 2]]], np.uint8)
    inst = np.array([[[1, 1, 0], [2, 0, 3]], [[0, 0, 0], [1, 0, 1]]], np.int16)
    scores = np.array([[1.0, 0.7, 0.4, 0.9], [1.0, 0.6, 1.0, 1.0]], np.float32)
    lab = WindowLabels(sem, inst, scores)
    want = np.array([[[0.7, 0.7, 1.0], [0.0, 1.0, 0.9]], [[1.0, 1.0, 1.0], [0.6, 0.0, 0.6]]], np.float32)
    assert np.array_equal(lab.confidence, want)
    f, v, u = np.array([0, 1, 0, 1]), np.array([1, 1, 0, 0]), np.array([2, 0, 0, 2])
    assert np.array_equal(lab.confidence_at(f, v, u), want[f, v, u])
    assert np.array_equal(lab.take(np.array([1])).confidence, want[1:])
    assert np.array_equal(WindowLabels(sem, inst).confidence, (sem != 255).astype(np.float32))  # no scores: 1


def test_nan_scores_count_as_zero_and_the_callers_table_is_kept():
    given = np.array([[np.nan, np.nan, 1.0, np.inf, -1.0, 2.0]], np.float32)
    lab = WindowLabels(np.zeros((1, 1, 5), np.uint8), np.arange(1, 6, dtype=np.int16)[None, None], given)
    assert np.array_equal(lab.confidence, np.array([[[0.0, 1.0, 1.0, 0.0, 1.0]]], np.float32))
    assert np.isnan(given[0, 1]) and given[0, 5] == 2.0


def test_labels_need_a_score_for_every_segment_id():
    with pytest.raises(ValueError, match="a score for every segment id"):
        WindowLabels(np.zeros((1, 1, 3), np.uint8), np.array([[[0, 1, 4]]], np.int16), np.ones((1, 4), np.float32))
    with pytest.raises(ValueError, match=">= 0"):
        WindowLabels(np.zeros((1, 1, 2), np.uint8), np.array([[[0, -1]]], np.int16))


def test_grow_threshold_outside_0_1_is_a_clear_error():
    with pytest.raises(ValueError, match="grow_threshold"):
        PanopticConfig(grow_threshold=-0.1)


def test_stuff_confidence_outside_0_1_is_a_clear_error():
    with pytest.raises(ValueError, match="stuff_confidence"):
        PanopticConfig(stuff_confidence=1.5)


def test_too_few_slots_is_a_clear_error(fitted):
    data, sem, inst, model = fitted
    with pytest.raises(ValueError, match="n_slots"):
        fit_panoptic(model, detector_like(sem, inst), data.is_train, data.depths, PanopticConfig(n_slots=3, steps=1))


def test_panoptic_phase_leaves_the_colour_model_alone(fitted):
    data, sem, inst, model = fitted
    before = [p.detach().clone() for p in model.field.parameters()]
    fit_panoptic(model, detector_like(sem, inst), data.is_train, data.depths,
                 PanopticConfig(steps=5, frames_per_step=2, rays_per_frame=64))
    assert all(torch.equal(a, b) for a, b in zip(before, model.field.parameters()))
