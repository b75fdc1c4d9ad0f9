"""rowmap.fusion on small synthetic frames: spheres in front of a camera at the origin (looking along +z), the
render's labels perturbed the way NeRF renders fail, the fused ids checked against the truth."""
from __future__ import annotations

import numpy as np
import pytest

from nerf.surfaces import unproject
from rowmap.fusion import Config, Frame, FruitModel, FruitModels, frame_evidence, fused_label, terms

K = np.array([200.0, 200.0, 48.0, 32.0])   # fx, fy, cx, cy of a 96 x 64 image
HW = (64, 96)
R = 0.03                                    # fruit radius, m
BACKGROUND_M = 1.5


def scene(centres: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(z-depth [H, W], index of the sphere each pixel sees, -1 = background) of spheres of radius R."""
    v, u = np.mgrid[0:HW[0], 0:HW[1]]
    d = np.stack([(u + 0.5 - K[2]) / K[0], (v + 0.5 - K[3]) / K[1], np.ones(HW)], -1)   # rays with z = 1
    depth, who = np.full(HW, BACKGROUND_M), np.full(HW, -1)
    for i, c in enumerate(centres):
        a, b, cc = (d ** 2).sum(-1), -2 * (d @ c), c @ c - R * R
        disc = b * b - 4 * a * cc
        t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        nearer = t < depth
        depth, who = np.where(nearer, t, depth), np.where(nearer, i, who)
    return depth, who


def model(centre: np.ndarray, cfg: Config) -> FruitModel:
    """A fruit model from points on the half of its sphere facing the camera (as its windows saw it)."""
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = centre + R * d
    front = ((pts - centre) * -centre).sum(1) > 0
    return FruitModel(class_id=2, points=pts[front]).refit(cfg)


def fuse(centres: list[np.ndarray], label: np.ndarray, depth: np.ndarray, segments: np.ndarray | None = None,
         cfg: Config | None = None, fruit: np.ndarray | None = None) -> np.ndarray:
    """Fused ids of one frame whose render paints `label` (fruit i has id i + 1) over the scene's depth, with
    the render's fruit probability `fruit` (None: not rendered)."""
    cfg = cfg or Config()
    models = FruitModels({i + 1: model(c, cfg) for i, c in enumerate(centres)})
    frame = Frame(frame_id=0, label=label, depth=depth, segments=segments, k=K, c2w=np.eye(4), fruit=fruit)
    return fused_label(frame=frame, models=models, owners={}, cfg=cfg)[0]


def test_two_touching_fruits_keep_their_own_pixels_where_the_render_bleeds_one_over_the_other():
    centres = [np.array([-0.03, 0.0, 0.5]), np.array([0.03, 0.0, 0.5])]
    depth, who = scene(centres)
    truth = who + 1
    label = truth.copy()
    cols = np.nonzero((who == 0).any(0))[0]
    bled = (who == 0) & (np.arange(HW[1])[None] >= cols.max() - 7)   # 8 columns of fruit 1 painted as fruit 2
    label[bled] = 2
    fused = fuse(centres, label, depth)
    v, u = np.nonzero(bled)
    off_b = np.linalg.norm(unproject(depth, K, np.eye(4), v, u) - centres[1], axis=1) > R + 2 * Config().margin_m
    assert off_b.sum() > 20          # near both spheres (shape cost rising from radius + margin) it may go either way
    assert (fused[v[off_b], u[off_b]] == 1).mean() > 0.9
    assert (fused[who >= 0] == truth[who >= 0]).mean() > 0.95 > (label[who >= 0] == truth[who >= 0]).mean()


def test_a_fruit_entering_at_the_image_border_takes_its_sliver_from_its_seen_surface():
    # fruit 2 enters at the left edge; the render paints its sliver as leaf
    centres = [np.array([0.0, 0.0, 0.5]), np.array([-0.135, 0.0, 0.5])]
    depth, who = scene(centres)
    sliver = who == 1
    assert 0 < sliver.sum() and np.nonzero(sliver)[1].max() < 8
    label = np.where(who == 0, 1, 0)
    fused = fuse(centres, label, depth)
    assert (fused[sliver] == 2).mean() > 0.8
    assert (fused[who == 0] == 1).all() and (fused[who < 0] == 0).all()
    # inside the image (no border band) a fruit the render shows well keeps its outline as painted
    inner = [np.array([0.0, 0.0, 0.5]), np.array([-0.06, 0.0, 0.5])]
    depth, who = scene(inner)
    label = np.where(who >= 0, who + 1, 0)
    edge = (who == 1) & (np.arange(HW[1])[None] < np.nonzero(who == 1)[1].min() + 2)
    label[edge] = 0
    fused = fuse(inner, label, depth)
    assert (fused[edge] == 0).all()


def test_a_sliver_of_a_fruit_behind_a_neighbour_goes_to_the_fruit_behind():
    front, back = np.array([0.0, 0.0, 0.45]), np.array([0.045, 0.0, 0.55])
    depth, who = scene([front, back])
    sliver = who == 1
    assert sliver.sum() > 20
    label = np.where(who >= 0, 1, 0)            # the render paints the fruit behind with the front fruit's id
    fused = fuse([front, back], label, depth)
    assert (fused[sliver] == 2).mean() > 0.9
    assert (fused[who == 0] == 1).all()


def test_a_sliver_the_render_s_labels_drop_goes_to_its_fruit_where_the_render_s_fruit_probability_is_high():
    front, back = np.array([0.0, 0.0, 0.45]), np.array([0.045, 0.0, 0.55])
    depth, who = scene([front, back])
    sliver = who == 1
    label = np.where(who == 0, 1, 0)           # the render's post-processing dropped the sliver: background
    assert (fuse([front, back], label, depth)[sliver] == 0).mean() > 0.9   # a background call without its doubt
    fruit = np.where(who >= 0, 0.85, 0.02)     # what the render's classes said before the post-processing
    fused = fuse([front, back], label, depth, fruit=fruit)
    assert (fused[sliver] == 2).mean() > 0.9 and (fused[who == 0] == 1).all() and (fused[who < 0] == 0).all()
    # a probable fruit far behind every fruit model (a leaf the render doubts) stays background
    fused = fuse([front, back], label, depth, fruit=np.full(HW, 0.85))
    assert (fused[who < 0] == 0).all()


def test_a_detector_segment_merging_two_fruits_does_not_merge_their_ids():
    centres = [np.array([-0.03, 0.0, 0.5]), np.array([0.03, 0.0, 0.5])]
    depth, who = scene(centres)
    label = who + 1
    merged = np.where(who >= 0, 7, 0)           # one detector segment over both fruits
    fused = fuse(centres, label, depth, segments=merged)
    assert (fused == label).all()
    # the render paints part of fruit 2 as leaf: the segment, named for fruit 1 (painted on most of it), still
    # shows a fruit there, and fruit 2's model says which
    u = np.nonzero(who == 1)[1]   # image columns of fruit 2
    leaf = (who == 1) & (np.arange(HW[1])[None] > u.mean())
    label[leaf] = 0
    fused = fuse(centres, label, depth, segments=merged)
    assert (fused[leaf] == 2).mean() > 0.5 and (fused[who == 0] == 1).all()   # all but the limb (0 before)


def test_the_halo_a_render_paints_around_a_fruit_is_background_unless_the_detector_shows_the_fruit_there():
    centre = np.array([0.0, 0.0, 0.5])
    depth, who = scene([centre])
    v, u = np.nonzero(who == 0)
    yy, xx = np.mgrid[0:HW[0], 0:HW[1]]
    r_px = (u.max() - u.min()) / 2
    halo = (np.hypot(yy - v.mean(), xx - u.mean()) < r_px + 4) & (who < 0)
    label = np.where((who == 0) | halo, 1, 0)
    fused = fuse([centre], label, depth)
    assert (fused[halo] == 0).all() and (fused[who == 0] == 1).all()
    # a halo on the fruit's own surface (the sensor sees the fruit there) is kept where the detector shows it
    depth_near = np.where(halo, depth[who == 0].max(), depth)
    fused = fuse([centre], label, depth_near, segments=np.where(label > 0, 3, 0))
    assert (fused[halo] == 1).mean() > 0.5


def test_each_term_can_be_switched_off_and_with_every_term_off_but_the_render_the_render_is_kept():
    centres = [np.array([-0.03, 0.0, 0.5]), np.array([0.03, 0.0, 0.5])]
    depth, who = scene(centres)
    label = np.where(who >= 0, 1, 0)            # one id over both fruits
    cfg = Config(terms_off=("detector", "shape", "surface", "order"))
    assert (fuse(centres, label, depth, cfg=cfg) == label).all()
    models = FruitModels({i + 1: model(c, Config()) for i, c in enumerate(centres)})
    ev = frame_evidence(frame=Frame(0, label, depth, None, K, np.eye(4)), models=models, owners={}, cfg=Config())
    for name, term in terms(ev, Config()).items():
        assert term.shape == (len(ev.pixels), len(ev.ids) + 1) and 0 <= term.min() and term.max() <= 1, name
    with pytest.raises(ValueError, match="unknown terms"):
        Config(terms_off=("colour",))


def test_frames_fused_on_several_threads_match_one_thread_frame_for_frame():
    """rowmap.fusion.fuse works on frames in threads; its frames come back in order and equal one thread's."""
    import time

    from rowmap.fusion import fuse as fuse_frames

    cfg = Config(refine_rounds=1)
    centres = [np.array([-0.03, 0.0, 0.5]), np.array([0.03, 0.0, 0.5])]
    depth, who = scene(centres)
    rng = np.random.default_rng(1)

    def load(fid: int) -> Frame:
        time.sleep(0.01 * (fid % 3))           # frames finish out of order on several threads
        label = who + 1
        noisy = rng_labels[fid] & (who >= 0)
        label[noisy] = 3 - label[noisy]         # the render swaps the two fruits on some pixels
        return Frame(frame_id=fid, label=label, depth=depth, segments=None, k=K, c2w=np.eye(4))

    rng_labels = {fid: rng.random(HW) < 0.1 for fid in range(8)}
    models = FruitModels({i + 1: model(c, cfg) for i, c in enumerate(centres)})
    one = list(fuse_frames(range(8), load, models, cfg, threads=1)[1])
    three = list(fuse_frames(range(8), load, models, cfg, threads=3)[1])
    assert [f for f, _ in three] == list(range(8))
    for (_, a), (_, b) in zip(one, three):
        np.testing.assert_array_equal(a, b)
    for fid, a in one:                       # and the fusion did its work: fewer wrong pixels than the render
        assert (a != who + 1).sum() < (rng_labels[fid] & (who >= 0)).sum()


@pytest.mark.parametrize("piece_px, groups", [(4, 1), (8, 2)])
def test_a_slot_splits_into_the_same_pixel_groups_at_320x180_and_at_1280x720(piece_px, groups):
    """A slot painted on a fruit and on a piece far behind it: the piece is a group of its own only when it is
    large enough as a share of the image, the same at 320x180 and in a 1280x720 render stored 4x larger."""
    from rowmap.fusion.association import slot_views

    sem, inst = np.zeros((180, 320), np.int64), np.zeros((180, 320), np.int64)
    depth = np.full((180, 320), 2.0)
    sem[80:100, 100:120], inst[80:100, 100:120], depth[80:100, 100:120] = 2, 1, 0.6    # the fruit
    sl = np.s_[20:20 + piece_px, 250:250 + piece_px]
    sem[sl], inst[sl], depth[sl] = 2, 1, 1.4                                             # the piece behind
    k = np.array([230.0, 230.0, 160.0, 90.0])
    counts = []
    for scale in (1, 4):
        up = lambda a: np.repeat(np.repeat(a, scale, 0), scale, 1)  # noqa: E731  nearest, as stored renders are
        views, _ = slot_views(up(sem), up(inst), up(depth), np.zeros((180 * scale, 320 * scale)), k * scale,
                              np.eye(4), [2, 3, 4], Config())
        counts.append(len(views))
    assert counts == [groups, groups]


def test_fuse_loads_each_frame_once_per_round_and_once_to_write_it():
    """Nothing is held per frame between rounds: every round loads each frame again, and so does the write."""
    from collections import Counter

    from rowmap.fusion import fuse

    cfg = Config(refine_rounds=2)
    centres = [np.array([0.0, 0.0, 0.5])]
    depth, who = scene(centres)
    models = FruitModels({1: model(centres[0], cfg)})
    calls = Counter()

    def load(fid):
        calls[fid] += 1
        return Frame(frame_id=fid, label=np.where(who >= 0, who + 1, 0), depth=depth, segments=None, k=K, c2w=np.eye(4))

    out = list(fuse([3, 5], load, models, cfg, threads=2)[1])
    assert [fid for fid, _ in out] == [3, 5]
    assert calls == {3: cfg.refine_rounds + 1, 5: cfg.refine_rounds + 1}
    assert (out[0][1][who >= 0] == 1).all()


def test_a_fruit_seen_only_as_a_shallow_cap_gets_a_sphere_of_the_given_size_behind_the_cap():
    cfg = Config()
    centre = np.array([0.02, 0.01, 0.5])
    rng = np.random.default_rng(1)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    toward_eye = -centre / np.linalg.norm(centre)
    cap = centre + R * d[d @ toward_eye > np.cos(np.radians(12))]   # what a view at the image border shows
    cap += rng.normal(scale=0.001, size=cap.shape)                  # the depth's noise
    assert FruitModel(class_id=2, points=cap).refit(cfg).centre is None   # a free fit to it is no fruit
    m = FruitModel(class_id=2, points=cap).refit(cfg, behind=(np.zeros(3), R))
    assert m.radius == R and np.linalg.norm(m.centre - centre) < R / 5   # the cap itself lies R from it
    assert m.surface is not None
    # the side comes from the camera: seen from behind the fruit, the sphere would lie in front of the cap
    assert FruitModel(class_id=2, points=cap).refit(cfg, behind=(2 * centre, R)).centre[2] < cap[:, 2].mean()


def test_a_fruit_without_a_sphere_keeps_to_its_pixels_and_takes_no_stray_detector_segment():
    """A fruit whose points fit no sphere has no extent: it keeps the pixels the render paints it on, but a
    detector segment that no render paints as a fruit (a false detection on the ground, in the border band where
    the render counts least) stays background instead of going to it."""
    centres = [np.array([-0.04, 0.0, 0.5]), np.array([0.04, 0.0, 0.5])]
    depth, who = scene(centres)
    label = who + 1
    segments = np.where(who >= 0, who + 1, 0)
    segments[:5, 30:60] = 9                                     # a false detection at the top border
    cfg = Config()
    models = FruitModels({1: model(centres[0], cfg), 2: FruitModel(class_id=2, points=np.zeros((0, 3)))})
    frame = Frame(frame_id=0, label=label, depth=depth, segments=segments, k=K, c2w=np.eye(4))
    fused = fused_label(frame=frame, models=models, owners={}, cfg=cfg)[0]
    assert (who[:5, 30:60] < 0).all() and (fused[:5, 30:60] == 0).all()
    assert (fused[who == 1] == 2).mean() > 0.95 and (fused[who == 0] == 1).mean() > 0.95


def test_a_frame_assigned_in_tiles_gets_the_ids_of_every_pixel_against_every_candidate(monkeypatch):
    """fused_label works tile by tile, each tile with the candidates that can win there (tiles): on a crowded
    frame with a render and a detector that err, a render that doubts its labels and a fruit without a sphere,
    its ids equal the argmin of the cost of every pixel against every candidate."""
    import rowmap.fusion.assignment as assignment
    from rowmap.fusion import cost

    rng = np.random.default_rng(11)
    centres = [np.array([x, y, z]) for x, y, z in zip(rng.uniform(-0.1, 0.1, 12), rng.uniform(-0.06, 0.06, 12),
                                                      rng.uniform(0.45, 0.7, 12))]
    depth, who = scene(centres)
    label = who + 1
    for _ in range(25):                                         # blobs painted as another fruit or as stuff
        v, u = rng.integers(0, HW[0] - 6), rng.integers(0, HW[1] - 6)
        label[v:v + 6, u:u + 6] = rng.integers(0, 13)
    segments = np.where(who >= 0, who + 1, 0)
    segments[segments == 3] = 4                                 # the detector merges fruits 3 and 4
    far = int(np.argmax([c[2] for c in centres]))
    u_far = K[0] * centres[far][0] / centres[far][2] + K[2]
    # a leaf in front, away from the far fruit and the border band, painted and detected as the far fruit
    blob = (slice(10, 15), slice(10, 15) if u_far > HW[1] / 2 else slice(HW[1] - 15, HW[1] - 10))
    depth[blob], label[blob], segments[blob] = 0.4, far + 1, 50
    cfg = Config()
    models = FruitModels({i + 1: model(c, cfg) for i, c in enumerate(centres)})
    models[5] = FruitModel(class_id=2, points=np.zeros((0, 3)))   # a fruit without a sphere
    fruit = rng.uniform(0.0, 1.0, HW)                          # the render's fruit probability, doubting anything
    frame = Frame(frame_id=0, label=label, depth=depth, segments=segments, k=K, c2w=np.eye(4), fruit=fruit)
    monkeypatch.setattr(assignment, "TILE_PX", 16)
    ev = frame_evidence(frame=frame, models=models, owners={}, cfg=cfg)
    c = cost(ev, cfg)
    c[np.arange(len(c)), ev.render] -= 1e-6
    every_pair = np.r_[0, ev.ids][c.argmin(1)]
    _, ev_tiled, ids = fused_label(frame=frame, models=models, owners={}, cfg=cfg)
    parts = list(assignment.tiles(ev=ev_tiled, shape=HW, cfg=cfg))
    assert len(parts) >= 12 and sum(len(r) * len(k) for r, k in parts) < 0.6 * len(ev.pixels) * len(ev.ids)
    no_sphere = [list(ev.ids).index(5) in k for _, k in parts]
    assert any(no_sphere) and not all(no_sphere)   # a fruit without a sphere: only in tiles that name it
    in_blob = np.isin(ev.pixels, np.ravel_multi_index(np.mgrid[blob].reshape(2, -1), HW))
    assert (ids[in_blob] == far + 1).any()                     # the far fruit wins pixels outside its halo box
    assert (ev_tiled.pixels == ev.pixels).all() and len(np.unique(ids)) > 8
    np.testing.assert_array_equal(ids, every_pair)


def test_a_detector_segment_the_render_paints_mostly_as_background_names_no_fruit_of_its_own():
    # fruit 2 enters at the left edge: the render paints its sliver as leaf but for a few pixels of fruit 1
    centres = [np.array([0.0, 0.0, 0.5]), np.array([-0.135, 0.0, 0.5])]
    depth, who = scene(centres)
    sliver = who == 1
    label = np.where(who == 0, 1, 0)
    sv, su = np.nonzero(sliver)
    label[sv[:3], su[:3]] = 1
    segments = np.where(sliver, 5, 0) + np.where(who == 0, 6, 0)
    cfg = Config()
    models = FruitModels({i + 1: model(c, cfg) for i, c in enumerate(centres)})
    frame = Frame(frame_id=0, label=label, depth=depth, segments=segments, k=K, c2w=np.eye(4))
    ev = frame_evidence(frame=frame, models=models, owners={}, cfg=cfg)
    option_of_1 = int(np.flatnonzero(ev.ids == 1)[0]) + 1
    assert (ev.detector[ev.segment == 5] == 0).all()             # some fruit, which one the models decide
    assert (ev.detector[ev.segment == 6] == option_of_1).all()   # painted mostly as fruit 1: fruit 1's
    assert (fused_label(frame=frame, models=models, owners={}, cfg=cfg)[0][sliver] == 2).mean() > 0.8



def test_a_round_refits_a_fruit_model_the_association_placed_off_to_the_pixels_it_was_given():
    """A window rendered fruit 2 most of its radius away from fruit 1, so its model (from the slots) lies there,
    and the render bleeds fruit 1 over fruit 2's near side. Assigned with that model, the bled pixels stay fruit
    1's (they lie outside fruit 2's sphere); a round gives fruit 2 the pixels the render and the detector show
    it, its model is refitted to them, and the next assignment gives most bled pixels back."""
    from rowmap.fusion import fuse as fuse_frames

    centres = [np.array([-0.03, 0.0, 0.5]), np.array([0.03, 0.0, 0.5])]
    depth, who = scene(centres)
    label = who + 1
    cols = np.nonzero((who == 1).any(0))[0]
    bled = (who == 1) & (np.arange(HW[1])[None] <= cols.min() + 7)   # 8 columns of fruit 2 painted as fruit 1
    label[bled] = 1
    segments = np.where(who >= 0, who + 1, 0)                       # the detector shows both fruits

    def load(fid: int) -> Frame:
        return Frame(frame_id=fid, label=label, depth=depth, segments=segments, k=K, c2w=np.eye(4))

    placed_off = centres[1] + np.array([0.7 * R, 0.0, 0.0])
    out = {}
    for rounds in (0, 1):
        cfg = Config(refine_rounds=rounds)
        models = FruitModels({1: model(centres[0], cfg), 2: model(placed_off, cfg)})
        final, frames = fuse_frames(range(3), load, models, cfg, threads=1)
        *_, (_, fused) = frames
        out[rounds] = (fused[bled] == 2).mean(), (fused[who >= 0] == (who + 1)[who >= 0]).mean(), final[2]
    assert np.allclose(out[0][2].centre, placed_off, atol=0.1 * R)        # no round: the model stays off
    assert np.linalg.norm(out[1][2].centre - centres[1]) < 0.05 * R         # a round: where its pixels are
    assert out[0][0] < 0.3 < 0.6 < out[1][0]
    assert out[0][1] < 0.9 < 0.94 < out[1][1]


def test_a_split_off_cluster_joins_its_neighbour_and_leaves_the_models_passed_in_unchanged():
    """Fruit 1's detector segments form two clusters seen together in three frames, one of them on fruit 2 (which
    the round gave no points): that cluster's segments become fruit 2's evidence and its points join fruit 2's
    model, while the models the round started from keep their points."""
    from rowmap.fusion.models import SegmentView, update

    cfg = Config()
    centres = [np.array([-0.03, 0.0, 0.5]), np.array([0.03, 0.0, 0.5])]
    models = FruitModels({i + 1: model(c, cfg) for i, c in enumerate(centres)})
    assert abs(models.typical_radius - R) < 0.1 * R
    before = {f: m.points.copy() for f, m in models.items()}
    cap = model(centres[1], cfg).points[:200]
    views = [SegmentView(frame=fid, segment=seg, n_px=300, centre=c, points=pts, eye=np.zeros(3)) for fid in range(3)
             for seg, c, pts in ((1, centres[0], models[1].points[:200]), (2, centres[1], cap))]
    out, owners = update(models, {1: [models[1].points]}, {1: views}, cfg)
    assert owners == {(fid, 1): 1 for fid in range(3)} | {(fid, 2): 2 for fid in range(3)}
    assert len(out[2].points) == len(before[2]) + 3 * len(cap)
    assert all(np.array_equal(models[f].points, before[f]) for f in models)


@pytest.mark.parametrize("apart_m, split", [(0.08, True), (0.038, False)])
def test_a_fruit_s_detector_segments_seen_in_one_frame_far_apart_are_two_fruits(apart_m, split):
    """A window painted two fruits as one slot (one model, its sphere around both); the detector shows them as
    two segments, seen together in one frame only. Segments farther apart than a fruit allows (8 cm; the row's
    other fruits have radius 3 cm) are two fruits: the second cluster's segments become a new fruit's evidence.
    Two pieces of one fruit (3.8 cm apart: a leaf cut its segment) stay one."""
    from rowmap.fusion.models import SegmentView, update

    cfg = Config()
    a, b = np.array([-apart_m / 2, 0.0, 0.5]), np.array([apart_m / 2, 0.0, 0.5])
    both = FruitModel(class_id=2, points=np.zeros((0, 3)), centre=(a + b) / 2, radius=apart_m / 2 + R / 2)
    others = {f: model(np.array([0.5 * f, 0.0, 0.5]), cfg) for f in (2, 3, 4)}   # the row's fruits, a metre away
    models = FruitModels({1: both, **others})
    views = [SegmentView(frame=fid, segment=seg, n_px=300, centre=c, points=model(c, cfg).points[:300], eye=np.zeros(3))
             for seg, c, fids in ((1, a, (0, 1, 2)), (2, b, (2, 3))) for fid in fids]
    out, owners = update(models, {}, {1: views}, cfg)
    if split:
        assert sorted(out) == [1, 2, 3, 4, 5]
        assert owners == {(0, 1): 1, (1, 1): 1, (2, 1): 1, (2, 2): 5, (3, 2): 5}
        assert np.linalg.norm(out[5].centre - b) < R / 3 and np.linalg.norm(out[1].centre - a) < R / 3
    else:
        assert sorted(out) == [1, 2, 3, 4] and owners == {}
