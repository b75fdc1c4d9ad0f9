"""Turn a ground-truth panoptic frame into what a still-image detector (Mask2Former-like) outputs.

Per frame: every visible fruit is missed with probability 1 - (1 - miss_rate)^(0.5 + 1.5 (1 - v)), v
being the visible share of its unoccluded projected area pi/4 (fx d / z)(fy l / z): occluded and cut-off
fruits are missed more often, fully visible ones less (miss_rate 0.15: 8 % when fully visible, 18 % when
half hidden, 28 % when almost hidden; 0 and 1 stay exact); a kept fruit is merged with a touching
neighbour with probability merge_rate and given a neighbouring ripeness class with probability
class_confusion_rate; its boundary moves in or out by a smooth, spatially varying offset of at
most boundary_px pixels; Poisson(false_pos_rate) fruit-sized blobs appear on leaves; segments
smaller than min_area_px are dropped; ids are 1..n in random order. Scores: U(0.75, 0.99) for a
correct segment, U(0.3, 0.7) for a merged, confused or false one. The semantic map is the ground
truth with undetected fruits turned into the stuff around them (plant in the near row, background
in the far row), a jittered plant/background border, the segments painted in, and a few void
pixels (255) on segment borders.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from pipeline.classes import VOID
from synthetic.scene import BACKGROUND, GREEN, MIXED, PLANT, RED

NEIGHBOUR_CLASS = {GREEN: (MIXED,), MIXED: (GREEN, RED), RED: (MIXED,)}


@dataclass(frozen=True)
class DetectorNoise:
    miss_rate: float
    false_pos_rate: float
    boundary_px: int
    merge_rate: float
    class_confusion_rate: float = 0.05
    void_rate: float = 0.03
    """Share of segment-border pixels (outside every segment) left void."""
    min_area_px: int = 12


@dataclass(frozen=True)
class FruitSizes:
    """Ground-truth sizes indexed by fruit id (index 0 unused), and the focal lengths in pixels."""

    diameter_m: np.ndarray
    length_m: np.ndarray
    near_row: np.ndarray
    fx: float
    fy: float


@dataclass
class Detection:
    semantic: np.ndarray
    """[H, W] uint8 class ids, 255 = void."""
    instance: np.ndarray
    """[H, W] uint16 segment ids 1..n (0 = stuff / none)."""
    segments: list[tuple[int, int, float]]
    """(segment_id, class_id, score) sorted by segment id."""
    stats: dict[str, int] = field(default_factory=dict)


def jitter_mask(mask: np.ndarray, max_px: float, rng: np.random.Generator, bias: float | None = None) -> np.ndarray:
    """Move the boundary of a binary mask in or out by a smooth offset field in [-max_px, max_px]
    (positive = grow). Works on the mask's bounding box; returns a new full-size bool mask."""
    if max_px <= 0 or not mask.any():
        return mask.copy()
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    pad = int(np.ceil(max_px)) + 2
    y0, y1 = max(0, ys.min() - pad), min(h, ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(w, xs.max() + pad + 1)
    crop = mask[y0:y1, x0:x1].astype(np.uint8)
    inside = cv2.distanceTransform(crop, cv2.DIST_L2, 3)
    outside = cv2.distanceTransform(1 - crop, cv2.DIST_L2, 3)
    signed = np.where(crop > 0, inside, 1.0 - outside)  # >= 1 inside, <= 0 outside: the border is at 0.5
    g = rng.uniform(-0.7, 0.7) * max_px if bias is None else bias
    coarse = rng.uniform(-1.0, 1.0, (4, 4)).astype(np.float32)
    fieldv = cv2.resize(coarse, (x1 - x0, y1 - y0), interpolation=cv2.INTER_CUBIC)
    offset = np.clip(g + 0.6 * max_px * fieldv, -max_px, max_px)
    out = np.zeros_like(mask)
    out[y0:y1, x0:x1] = signed + offset > 0.5
    return out


Box = tuple[int, int, int, int]
"""(v0, v1, u0, u1): rows v0..v1-1 and columns u0..u1-1 of an image."""


def _grown(sl: tuple[slice, slice], margin: int, h: int, w: int) -> Box:
    """The box of ndimage.find_objects slices grown by `margin` pixels on every side, inside an h x w image."""
    return (max(0, sl[0].start - margin), min(h, sl[0].stop + margin), max(0, sl[1].start - margin),
            min(w, sl[1].stop + margin))


def _in(img: np.ndarray, box: Box) -> np.ndarray:
    """The view of `img` inside `box`."""
    return img[box[0]:box[1], box[2]:box[3]]


def _blob(h: int, w: int, cy: int, cx: int, ay: float, ax: float, angle_deg: float) -> np.ndarray:
    m = np.zeros((h, w), np.uint8)
    cv2.ellipse(m, (int(cx), int(cy)), (max(1, int(round(ax))), max(1, int(round(ay)))), angle_deg, 0, 360, 1, -1)
    return m.astype(bool)


def detect(sem: np.ndarray, inst: np.ndarray, depth_m: np.ndarray, sizes: FruitSizes, noise: DetectorNoise,
           rng: np.random.Generator) -> Detection:
    """Ground-truth semantic [H, W], instance [H, W] (fruit ids) and depth [H, W] metres -> Detection."""
    h, w = sem.shape
    stats = {"visible": 0, "missed": 0, "merged": 0, "confused": 0, "false_pos": 0, "dropped_small": 0}
    ids, areas = np.unique(inst[inst > 0], return_counts=True)
    stats["visible"] = len(ids)
    # each fruit is worked on in its box, grown by the reach of the merge ring and of jitter_mask's crop
    margin = 3 + int(np.ceil(noise.boundary_px))
    boxes = {i: _grown(sl, margin, h, w) for i, sl in enumerate(ndimage.find_objects(inst), start=1) if sl}
    area_of = dict(zip(ids.tolist(), areas.tolist()))
    segments: list[tuple[Box, np.ndarray, int, float]] = []   # (box, mask inside the box, class, score)
    used: set[int] = set()
    for j in rng.permutation(len(ids)):
        fid, area = int(ids[j]), int(areas[j])
        if fid in used:
            continue
        used.add(fid)
        box = boxes[fid]
        crop = _in(inst, box)
        mask = crop == fid
        z = float(np.median(_in(depth_m, box)[mask])) + 0.5 * float(sizes.diameter_m[fid])
        full = np.pi / 4 * (sizes.fx * sizes.diameter_m[fid] / z) * (sizes.fy * sizes.length_m[fid] / z)
        vis = min(1.0, area / max(full, 1.0))
        if rng.random() < 1.0 - (1.0 - noise.miss_rate) ** (0.5 + 1.5 * (1.0 - vis)):
            stats["missed"] += 1
            continue
        klass = int(np.bincount(_in(sem, box)[mask]).argmax())
        score = rng.uniform(0.75, 0.99)
        if rng.random() < noise.merge_rate:
            ring = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=3 + noise.boundary_px) > 0
            near = [int(n) for n in np.unique(crop[ring & (crop > 0) & ~mask]) if int(n) not in used]
            if near:
                other = near[int(rng.integers(len(near)))]
                used.add(other)
                box = tuple(f(a, b) for f, a, b in zip((min, max, min, max), box, boxes[other]))
                crop = _in(inst, box)
                if area_of[other] > area:
                    klass = int(np.bincount(_in(sem, box)[crop == other]).argmax())
                mask = (crop == fid) | (crop == other)
                score = rng.uniform(0.3, 0.7)
                stats["merged"] += 1
        if rng.random() < noise.class_confusion_rate and klass in NEIGHBOUR_CLASS:
            klass = int(rng.choice(NEIGHBOUR_CLASS[klass]))
            score = rng.uniform(0.3, 0.7)
            stats["confused"] += 1
        segments.append((box, jitter_mask(mask, noise.boundary_px, rng), klass, score))
    # false positives: fruit-sized blobs on leaves, mostly taken for green fruit
    plant_px = np.flatnonzero((sem.ravel() == PLANT) & (depth_m.ravel() > 0))
    for _ in range(rng.poisson(noise.false_pos_rate)):
        if not len(plant_px):
            break
        p = int(plant_px[rng.integers(len(plant_px))])
        cy, cx = divmod(p, w)
        z = float(depth_m[cy, cx])
        ax = sizes.fx * rng.uniform(0.02, 0.04) / z
        blob = _blob(h, w, cy, cx, ax * rng.uniform(0.7, 1.4), ax, rng.uniform(0, 180))
        blob = jitter_mask(blob, max(1, noise.boundary_px), rng) & (inst == 0)
        segments.append(((0, h, 0, w), blob, int(rng.choice([GREEN, MIXED, RED], p=[0.6, 0.2, 0.2])),
                         rng.uniform(0.3, 0.7)))
        stats["false_pos"] += 1

    out_sem = sem.astype(np.uint8).copy()
    near = sizes.near_row[inst]
    things = inst > 0
    out_sem[things & near] = PLANT
    out_sem[things & ~near] = BACKGROUND
    # the plant/background border is not exact either
    plant = out_sem == PLANT
    moved = jitter_mask(plant, min(1.0, float(noise.boundary_px)), rng, bias=0.0) if noise.boundary_px else plant
    out_sem[moved & ~plant & (out_sem == BACKGROUND)] = PLANT
    out_sem[plant & ~moved] = BACKGROUND

    out_inst = np.zeros((h, w), np.uint16)
    kept: list[tuple[int, float]] = []
    for k in rng.permutation(len(segments)):
        box, mask, klass, score = segments[k]
        mask = mask & (_in(out_inst, box) == 0)
        if mask.sum() < noise.min_area_px:
            stats["dropped_small"] += 1
            continue
        kept.append((klass, score))
        _in(out_inst, box)[mask] = len(kept)
        _in(out_sem, box)[mask] = klass
    # ids carry no meaning from frame to frame: 1..n in random order
    perm = np.concatenate([[0], rng.permutation(len(kept)) + 1]).astype(np.uint16)
    out_inst = perm[out_inst]
    table = sorted((int(perm[i + 1]), int(c), round(float(s), 4)) for i, (c, s) in enumerate(kept))
    if noise.void_rate > 0 and kept:
        border = cv2.morphologyEx(out_inst, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        out_sem[border & (out_inst == 0) & (rng.random((h, w)) < noise.void_rate)] = VOID
    stats["segments"] = len(table)
    return Detection(out_sem, out_inst, table, stats)
