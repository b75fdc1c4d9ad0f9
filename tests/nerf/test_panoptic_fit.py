import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from scene_fixture import tiny_window  # noqa: E402

from nerf.config import PanopticConfig, preset  # noqa: E402
from nerf.panoptic.labels import WindowLabels  # noqa: E402
from nerf.panoptic.post import panoptic_labels  # noqa: E402
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
    return WindowLabels(sem.astype(np.uint8), out, np.ones(sem.shape, np.float32))


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


def test_all_void_labels_train_nothing_and_still_render(fitted):
    data, sem, _, model = fitted
    void = WindowLabels(np.full(sem.shape, 255, np.uint8), np.zeros(sem.shape, np.int32), np.zeros(sem.shape, np.float32))
    pres = fit_panoptic(model, void, data.is_train, data.depths, PanopticConfig(steps=5))
    assert pres.steps == 0 and pres.assignments == 0
    r = render_panoptic(model, pres, 0)
    assert np.isfinite(r["rgb"].numpy()).all() and r["semantic"].max() < 5


def test_window_without_fruit_detections_skips_the_instance_part(fitted):
    data, sem, inst, model = fitted
    plant = np.where(np.isin(sem, [2, 3, 4]), 1, sem).astype(np.uint8)   # the detector saw no fruit at all
    labels = WindowLabels(plant, np.zeros_like(inst), np.ones(sem.shape, np.float32))
    cfg = PanopticConfig(steps=40, stuff_only_steps=10, frames_per_step=2, rays_per_frame=64)
    pres = fit_panoptic(model, labels, data.is_train, data.depths, cfg)
    assert pres.instances_skipped and pres.steps == 10 and pres.assignments == 0 and not pres.cfg.instances
    assert pres.params < fit_panoptic(model, detector_like(sem, inst), data.is_train, data.depths,
                                      PanopticConfig(steps=1)).params            # instance head not counted
    r = render_panoptic(model, load_panoptic(pres.state(), model), 1)
    assert (r["instance"] == 0).all()


def test_nan_confidence_is_treated_as_zero():
    lab = WindowLabels(np.zeros((1, 2, 2), np.uint8), np.zeros((1, 2, 2), np.int32),
                       np.array([[[np.nan, 1.0], [np.inf, -1.0]]], np.float32))
    assert np.array_equal(lab.confidence, np.array([[[0.0, 1.0], [1.0, 0.0]]], np.float32))


def test_post_processing_opens_masks_drops_specks_and_unifies_the_class():
    h, w, cfg = 12, 12, PanopticConfig(min_segment_px=4)
    p_sem = np.zeros((h, w, 5))
    p_sem[..., 1] = 1.0                        # plant everywhere ...
    p_sem[2:8, 2:8] = 0
    p_sem[2:8, 2:8, 4] = 1.0                   # ... a red fruit block
    p_sem[2, 2, 4], p_sem[2, 2, 3] = 0, 1.0    # one pixel of it says 'mixed'
    p_sem[10, 10, 1], p_sem[10, 10, 2] = 0.3, 0.7   # a one-pixel green speck on the plant
    p_inst = np.zeros((h, w, 8))
    p_inst[..., 0] = 1.0
    p_inst[2:8, 2:8, 0], p_inst[2:8, 2:8, 5] = 0, 1.0
    p_inst[10, 10, 0], p_inst[10, 10, 3] = 0, 1.0
    sem, inst = panoptic_labels(p_sem, p_inst, cfg)
    assert (inst[2:8, 2:8] == 5).all() and (sem[2:8, 2:8] == 4).all()  # the majority class wins
    assert inst[10, 10] == 0 and sem[10, 10] == 1                       # the speck becomes stuff
    assert (inst[sem < 2] == 0).all()


def test_fruit_cut_by_the_image_border_keeps_its_thin_strip():
    h, w, cfg = 20, 12, PanopticConfig(min_segment_px=12)
    p_sem = np.zeros((h, w, 5))
    p_sem[..., 1] = 1.0
    p_sem[4:16, :2, 1], p_sem[4:16, :2, 2] = 0.0, 1.0   # a 2-pixel-wide strip of fruit at the left border
    p_sem[4:16, 6:8, 1], p_sem[4:16, 6:8, 2] = 0.0, 1.0  # the same strip inside the image: opened away
    p_inst = np.zeros((h, w, 4))
    p_inst[..., 0] = 1.0
    p_inst[4:16, :2, 0], p_inst[4:16, :2, 1] = 0.0, 1.0
    p_inst[4:16, 6:8, 0], p_inst[4:16, 6:8, 2] = 0.0, 1.0
    sem, inst = panoptic_labels(p_sem, p_inst, cfg)
    assert (inst[4:16, :2] == 1).all() and (sem[4:16, :2] == 2).all()
    assert (inst[:, 2:] != 1).all() and (inst == 2).sum() == 0


def test_fruit_of_uncertain_ripeness_is_a_fruit_not_plant():
    # the three ripeness classes share a fruit's probability: each is below 'plant', together above it
    cfg = PanopticConfig(min_segment_px=1, grow_threshold=1.0)
    p_sem = np.zeros((6, 6, 5))
    p_sem[..., 1] = 1.0
    p_sem[1:5, 1:5] = [0.05, 0.35, 0.25, 0.15, 0.2]
    p_inst = np.zeros((6, 6, 3))
    p_inst[..., 0] = 1.0
    p_inst[1:5, 1:5] = [0.2, 0.7, 0.1]
    sem, inst = panoptic_labels(p_sem, p_inst, cfg)
    assert (sem[1:5, 1:5] == 2).all() and (inst[1:5, 1:5] == 1).all()
    assert (sem[0] == 1).all() and (inst[0] == 0).all()


def test_weak_rim_joins_the_touching_fruit_but_weak_evidence_alone_stays_stuff():
    h, w = 16, 16
    p_sem = np.zeros((h, w, 5))
    p_sem[..., 1] = 1.0
    p_sem[4:10, 4:10] = [0, 0.2, 0, 0, 0.8]        # the sure core of a red fruit
    p_sem[4:10, 10:12] = [0, 0.6, 0, 0, 0.4]       # its rim: fruit probability 0.4, under 'plant'
    p_sem[12:16, 12:16] = [0, 0.6, 0, 0, 0.4]      # the same weak evidence away from any fruit
    p_inst = np.zeros((h, w, 4))
    p_inst[..., 0] = 1.0
    p_inst[4:10, 4:12] = [0.1, 0, 0.9, 0]
    p_inst[12:16, 12:16] = [0.1, 0, 0.9, 0]
    on = panoptic_labels(p_sem, p_inst, PanopticConfig(min_segment_px=4, grow_threshold=0.3))
    off = panoptic_labels(p_sem, p_inst, PanopticConfig(min_segment_px=4, grow_threshold=1.0))
    for sem, inst in (on, off):
        assert (inst[4:10, 4:10] == 2).all() and (sem[4:10, 4:10] == 4).all()
        assert (inst[12:, 12:] == 0).all() and (sem[12:, 12:] == 1).all()
    assert (on[1][4:10, 10:12] == 2).all() and (on[0][4:10, 10:12] == 4).all()
    assert (off[1][4:10, 10:12] == 0).all()


def test_growth_stops_at_a_depth_jump():
    p_sem = np.zeros((10, 16, 5))
    p_sem[..., 1] = 1.0
    p_sem[2:8, 2:8] = [0, 0.2, 0, 0, 0.8]          # sure core at 0.60 m
    p_sem[2:8, 8:14] = [0, 0.6, 0, 0, 0.4]         # weak rim: columns 8-10 on the fruit, 11-13 on the wall
    p_inst = np.zeros((10, 16, 3))
    p_inst[..., 0] = 1.0
    p_inst[2:8, 2:14] = [0.1, 0.9, 0]
    depth = np.full((10, 16), 1.5)
    depth[2:8, 2:11] = 0.6 + 0.001 * np.arange(9)
    cfg = PanopticConfig(min_segment_px=4, grow_threshold=0.3, grow_depth_m=0.02)
    _, inst = panoptic_labels(p_sem, p_inst, cfg, depth)
    assert (inst[2:8, 2:11] == 1).all() and (inst[2:8, 11:] == 0).all()
    _, no_depth = panoptic_labels(p_sem, p_inst, cfg)
    assert (no_depth[2:8, 2:14] == 1).all()


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


def test_thing_oversampling_is_undone_by_importance_weights():
    from nerf.pixel_sampling import draw_label_pixels

    sem = np.ones((40, 50), np.uint8)
    things = np.zeros((40, 50), bool)
    things[:4, :5] = True                        # 1 % of the pixels are fruit
    sem[things] = 4
    px, w = draw_label_pixels(sem != 255, things, 20000, 0.5, np.random.default_rng(0))
    on = things.ravel()[px]
    assert 0.45 < on.mean() < 0.55                # half the rays land on fruit ...
    assert abs((w * on).sum() / w.sum() - 0.01) < 0.003   # ... but weigh as 1 % of the image
    assert w.max() == 1.0 and (w > 0).all()


def _sphere_view(centre: np.ndarray, radius: float, cam_x: float, h: int = 40, w: int = 60
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth [H, W] of a sphere (background wall at z = 2 m) seen by a camera at (cam_x, 0, 0) looking
    along +z, the sphere mask, and the camera's c2w."""
    k = np.array([50.0, 50.0, w / 2, h / 2])
    v, u = np.mgrid[0:h, 0:w]
    d = np.stack([(u + 0.5 - k[2]) / k[0], (v + 0.5 - k[3]) / k[1], np.ones((h, w))], -1)   # z = 1 rays
    o = np.array([cam_x, 0.0, 0.0])
    oc = o - centre
    a, b, c = (d * d).sum(-1), 2 * (d * oc).sum(-1), oc @ oc - radius ** 2
    disc = b * b - 4 * a * c
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    hit = np.isfinite(t)
    depth = np.where(hit, t, 2.0)                                   # z-depth (rays have z = 1)
    c2w = np.eye(4)
    c2w[0, 3] = cam_x
    return depth, hit, c2w


def test_complete_instances_gives_a_fruit_its_stuff_labelled_side_but_not_the_leaf_in_front():
    from nerf.panoptic.complete import complete_instances

    centre, radius = np.array([0.0, 0.0, 0.5]), 0.04
    frames, poses = [], []
    for cam_x in (-0.02, 0.0, 0.02):
        depth, hit, c2w = _sphere_view(centre, radius, cam_x)
        sem = np.where(hit, 2, 1).astype(np.uint8)
        inst = np.where(hit, 7, 0).astype(np.int32)
        frames.append({"semantic": sem, "instance": inst, "depth": depth})
        poses.append(c2w)
    last = frames[-1]
    truth = last["instance"].copy()
    cols = np.arange(truth.shape[1])[None, :].repeat(truth.shape[0], 0)
    stuffed = (truth == 7) & (cols >= 30)                           # the head called half the fruit plant
    last["instance"][stuffed], last["semantic"][stuffed] = 0, 1
    leaf = (truth == 7) & (cols < 30) & (np.arange(truth.shape[0])[:, None] == 20)
    last["depth"][leaf] = 0.3                                      # a leaf 15 cm in front of the fruit
    last["instance"][leaf], last["semantic"][leaf] = 0, 1
    other = (truth == 0) & (cols == 0)
    last["instance"][other] = 9                                    # another instance's pixels stay its own
    k = np.array([[50.0, 50.0, 30.0, 20.0]] * 3)
    cfg = PanopticConfig(complete_margin_m=0.005, complete_min_points=50)
    added = complete_instances(frames, k, np.stack(poses), cfg)
    assert added == int(stuffed.sum())
    assert (last["instance"][stuffed] == 7).all() and (last["semantic"][stuffed] == 2).all()
    assert (last["instance"][leaf] == 0).all() and (last["instance"][other] == 9).all()
    assert (last["instance"][(truth == 0) & ~other] == 0).all()     # the wall behind stays stuff
    off = [dict(f, instance=f["instance"].copy()) for f in frames]
    assert complete_instances(off, k, np.stack(poses), PanopticConfig(instances=False)) == 0


def test_completion_by_ray_takes_a_rim_whose_depth_fell_behind_but_not_the_wall_around_the_fruit():
    from nerf.panoptic.complete import complete_instances, rays_through_core

    centre, radius = np.array([0.0, 0.0, 0.5]), 0.04
    frames, poses = [], []
    for cam_x in (-0.02, 0.0, 0.02):
        depth, hit, c2w = _sphere_view(centre, radius, cam_x)
        frames.append({"semantic": np.where(hit, 2, 1).astype(np.uint8), "instance": np.where(hit, 7, 0).astype(np.int32),
                       "depth": depth})
        poses.append(c2w)
    k = np.array([[50.0, 50.0, 30.0, 20.0]] * 3)
    last, c2w = frames[-1], poses[-1]
    truth = last["instance"].copy()
    v, u = np.nonzero(truth == 7)
    _, closest = rays_through_core(last["depth"], k[2], c2w, v, u, centre[None], np.array([radius]), 0.0)
    core = np.zeros_like(truth, bool)
    core[v, u] = closest[:, 0] <= 0.7 * radius
    rim = (truth == 7) & ~core
    # the head called the fruit's right half stuff, and there the rendered depth slid to the wall behind
    cols = np.arange(truth.shape[1])[None, :].repeat(truth.shape[0], 0)
    lost = (truth == 7) & (cols >= 28)
    last["instance"][lost], last["semantic"][lost], last["depth"][lost] = 0, 1, 2.0
    leaf = lost & (np.arange(truth.shape[0])[:, None] == 20)
    last["depth"][leaf] = 0.3                                      # a leaf in front of the fruit stays a leaf
    cfg = PanopticConfig(complete_margin_m=0.005, complete_min_points=50, complete_core=0.7)
    off = [dict(f, instance=f["instance"].copy(), semantic=f["semantic"].copy()) for f in frames]
    assert complete_instances(off, k, np.stack(poses), replace(cfg, complete_core=0.0)) == 0   # depth test only
    added = complete_instances(frames, k, np.stack(poses), cfg)
    taken = lost & core & ~leaf
    assert added == int(taken.sum()) > 0
    assert (last["instance"][taken] == 7).all() and (last["semantic"][taken] == 2).all()
    assert (last["instance"][lost & rim] == 0).all() and (last["instance"][leaf] == 0).all()
    assert (last["instance"][truth == 0] == 0).all()                # the wall around the fruit stays stuff
