"""2D post-processing of rendered panoptic distributions (nerf/panoptic/post.py)."""
import numpy as np

from nerf.config import PanopticConfig
from nerf.panoptic.post import panoptic_labels


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
