"""2D post-processing of rendered panoptic distributions into semantic and instance images."""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from nerf.config import PanopticConfig


def panoptic_labels(p_sem: np.ndarray, p_inst: np.ndarray, cfg: PanopticConfig,
                    depth: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel distributions [H, W, D] / [H, W, N] -> semantic uint8 and instance int32 images
    (labels_from_slots with each pixel's most likely thing slot)."""
    return labels_from_slots(p_sem, best_slot(p_inst), cfg, depth)


def best_slot(p_inst: np.ndarray) -> np.ndarray:
    """The most likely thing slot (1..N-1) of each pixel's instance distribution [..., N] (int64 [...])."""
    return p_inst[..., 1:].argmax(-1) + 1


def labels_from_slots(p_sem: np.ndarray, slot: np.ndarray, cfg: PanopticConfig,
                      depth: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel class distributions [H, W, D] and most likely thing slots [H, W] (best_slot) -> semantic uint8
    and instance int32 images.

    A pixel is a thing when the fruit classes together are more likely than each stuff class (the
    ripeness classes split a fruit's probability three ways, so a plain argmax over the five classes
    calls a fruit of uncertain ripeness "plant"); it then takes the most likely thing class and the most
    likely thing slot. Instances grow into touching pixels of the same slot whose fruit
    probability exceeds cfg.grow_threshold (hysteresis) and, given the rendered `depth` [H, W], whose depth
    lies within cfg.grow_depth_m of the instance's sure pixels. Post-processing: each instance mask
    gets one 3x3 opening (erosion then dilation; the image border does not erode, so a fruit cut by it
    keeps its thin visible strip), instances smaller than cfg.min_segment_px are dropped,
    an instance's pixels take its majority thing class, and dropped pixels take their most likely
    stuff class with instance 0."""
    things = np.array(cfg.thing_classes, np.int64)
    stuff = np.array([c for c in range(p_sem.shape[-1]) if c not in set(cfg.thing_classes)], np.int64)
    stuff_sem = stuff[p_sem[..., stuff].argmax(-1)] if stuff.size else np.zeros(p_sem.shape[:-1], np.int64)
    best_thing = things[p_sem[..., things].argmax(-1)] if things.size else stuff_sem
    p_fruit = p_sem[..., things].sum(-1)                                   # 0 without thing classes
    is_thing = (p_fruit >= (p_sem[..., stuff].max(-1) if stuff.size else 0.0)) & (things.size > 0)
    if cfg.instances and things.size and cfg.grow_threshold < 1.0:
        is_thing = grow_instances(is_thing, slot, p_fruit > cfg.grow_threshold, depth, cfg.grow_depth_m)
    sem = np.where(is_thing, best_thing, stuff_sem)
    if not cfg.instances:  # semantic only: thing pixels keep their class, no instance ids
        return sem.astype(np.uint8), np.zeros(sem.shape, np.int32)
    inst = np.where(is_thing, slot, 0).astype(np.int32)
    out_sem = sem.astype(np.uint8)
    out_inst = np.zeros_like(inst)
    kernel = np.ones((3, 3), bool)
    for sl_id in np.unique(inst[inst > 0]):
        mask = inst == sl_id
        opened = ndimage.binary_dilation(ndimage.binary_erosion(mask, kernel, border_value=1), kernel) & mask
        if opened.sum() < cfg.min_segment_px:
            continue
        classes, counts = np.unique(sem[opened], return_counts=True)
        thing_counts = [(n_, c) for c, n_ in zip(classes, counts) if c in set(cfg.thing_classes)]
        out_sem[opened] = max(thing_counts)[1] if thing_counts else out_sem[opened]
        out_inst[opened] = sl_id
    dropped = is_thing & (out_inst == 0)
    out_sem[dropped] = stuff_sem[dropped]
    return out_sem, out_inst


def grow_instances(sure: np.ndarray, slot: np.ndarray, weak: np.ndarray, depth: np.ndarray | None = None,
                   depth_margin_m: float = 0.0) -> np.ndarray:
    """Hysteresis: `sure` [H, W] plus every 8-connected region of `weak` pixels of one slot that touches a
    sure pixel of that slot. With `depth`, a weak pixel must also lie within `depth_margin_m` of the depth
    range (5th-95th percentile) of the slot's sure pixels: a fruit's rim, not the leaf or the wall behind."""
    out = sure.copy()
    eight = np.ones((3, 3), bool)
    for sl_id in np.unique(slot[sure]):
        core = sure & (slot == sl_id)
        cand = weak & (slot == sl_id)
        if depth is not None:
            lo, hi = np.percentile(depth[core], [5, 95])
            cand &= (depth >= lo - depth_margin_m) & (depth <= hi + depth_margin_m)
        regions, n = ndimage.label(cand | core, eight)
        if n:
            touching = np.unique(regions[core])
            out |= np.isin(regions, touching[touching > 0])
    return out
