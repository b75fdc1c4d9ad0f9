"""Turn ground-truth panoptic labels into what a still-image detector (Mask2Former-like) outputs:
per-frame shuffled ids, missed fruits, false positives, noisy boundaries, merged neighbours,
confused ripeness classes and confidences that are lower on the wrong segments."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.classes import THING_IDS

KERNEL = np.ones((3, 3), np.uint8)


@dataclass(frozen=True)
class DetectorNoise:
    miss_rate: float
    false_pos_rate: float
    boundary_px: int
    merge_rate: float
    class_confusion_rate: float = 0.05
    min_area_px: int = 12


def _morph(mask: np.ndarray, k: int) -> np.ndarray:
    if k == 0:
        return mask
    op = cv2.dilate if k > 0 else cv2.erode
    return op(mask.astype(np.uint8), KERNEL, iterations=abs(k)).astype(bool)


def corrupt(sem: np.ndarray, inst: np.ndarray, noise: DetectorNoise, rng: np.random.Generator,
            fruit_px: float) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int, float]]]:
    """GT semantic [H, W] and instance [H, W] -> detector semantic (uint8), instance (uint16) and
    [(segment_id, class_id, score)]. `fruit_px` is a typical fruit diameter in pixels (false positive size)."""
    h, w = sem.shape
    things = np.isin(sem, THING_IDS) & (inst > 0)
    ids, areas = np.unique(inst[things], return_counts=True)
    out_sem = sem.copy()
    out_sem[things] = 1  # fruits the detector does not report look like plant
    segments: list[tuple[np.ndarray, int, float]] = []
    used: set[int] = set()
    order = rng.permutation(len(ids))
    for j in order:
        fid, area = int(ids[j]), int(areas[j])
        if fid in used:
            continue
        used.add(fid)
        mask = inst == fid
        klass = int(np.bincount(sem[mask]).argmax())
        # small / occluded fruits are missed more often
        p_miss = min(1.0, noise.miss_rate * (1.0 + 2.0 * max(0.0, 1 - area / (0.5 * fruit_px ** 2))))
        if rng.random() < p_miss:
            continue
        score = rng.uniform(0.75, 0.99)
        if rng.random() < noise.merge_rate:
            near = np.unique(inst[_morph(mask, 3) & things & ~mask])
            near = [int(n) for n in near if n not in used]
            if near:
                other = near[0]
                used.add(other)
                mask = mask | (inst == other)
                score = rng.uniform(0.45, 0.8)
        if rng.random() < noise.class_confusion_rate:
            klass = int(np.clip(klass + rng.choice([-1, 1]), min(THING_IDS), max(THING_IDS)))
            score = min(score, rng.uniform(0.4, 0.75))
        mask = _morph(mask, int(rng.integers(-noise.boundary_px, noise.boundary_px + 1)))
        segments.append((mask, klass, score))
    for _ in range(rng.poisson(noise.false_pos_rate)):
        cy, cx = int(rng.integers(0, h)), int(rng.integers(0, w))
        if sem[cy, cx] != 1:  # false positives appear on plants (leaves look like green fruit)
            continue
        fp = np.zeros((h, w), np.uint8)
        axes = (max(2, int(fruit_px * rng.uniform(0.25, 0.5))), max(2, int(fruit_px * rng.uniform(0.3, 0.6))))
        cv2.ellipse(fp, (cx, cy), axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        segments.append((fp.astype(bool) & (sem != 0), int(rng.choice(THING_IDS, p=[0.6, 0.2, 0.2])),
                         rng.uniform(0.3, 0.7)))
    out_inst = np.zeros((h, w), np.uint16)
    table = []
    for k, (mask, klass, score) in enumerate(segments):
        mask = mask & (out_inst == 0)
        if mask.sum() < noise.min_area_px:
            continue
        sid = len(table) + 1
        out_inst[mask] = sid
        out_sem[mask] = klass
        table.append((sid, klass, float(round(score, 4))))
    # per-frame ids carry no meaning: shuffle them
    if table:
        perm = rng.permutation(len(table)) + 1
        remap = np.zeros(len(table) + 1, np.uint16)
        remap[1:] = perm
        out_inst = remap[out_inst]
        table = sorted(((int(perm[s - 1]), c, sc) for s, c, sc in table))
    # boundary pixels between classes are sometimes left void, as a detector's low-confidence band
    edges = cv2.morphologyEx(out_sem, cv2.MORPH_GRADIENT, KERNEL) > 0
    void = edges & (rng.random((h, w)) < 0.15) & (out_inst == 0)
    out_sem[void] = 255
    return out_sem.astype(np.uint8), out_inst, table
