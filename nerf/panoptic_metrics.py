"""Panoptic quality (PQ = SQ x RQ), mean IoU and fruit-ID consistency on label images.

PQ follows the COCO panoptic reference: a segment is a (class, instance) pair for things and one
segment per class for stuff; a predicted and a ground-truth segment of the same class match when
IoU > 0.5, where the union leaves out predicted pixels that fall on ground-truth void; an unmatched
predicted segment is a false positive unless more than half of it lies on void. Per class over a
whole set of images:

    PQ_c = sum_{matches} IoU / (TP + FP/2 + FN/2),   SQ_c = sum IoU / TP,   RQ_c = TP / (TP + FP/2 + FN/2)

and PQ is the mean of PQ_c over the classes with TP + FP + FN > 0. Example (torchmetrics' documented
PanopticQuality case, things {0, 1}, stuff {6, 7}) gives PQ = 0.5463.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

VOID = 255


def _segments(sem: np.ndarray, inst: np.ndarray, things: set[int], classes: set[int]) -> np.ndarray:
    """Segment key per pixel: class * 2^20 + instance for things, class * 2^20 for stuff; -1 = not a segment."""
    sem = sem.astype(np.int64)
    inst = inst.astype(np.int64)
    is_thing = np.isin(sem, list(things))
    key = sem * (1 << 20) + np.where(is_thing, inst, 0)
    valid = np.isin(sem, list(classes))
    return np.where(valid, key, -1)


@dataclass
class PanopticAccumulator:
    """Accumulates TP / FP / FN / IoU per class over images; `compute()` gives PQ, SQ, RQ."""

    things: set[int]
    stuff: set[int]
    void: int = VOID
    tp: dict[int, int] = field(default_factory=dict)
    fp: dict[int, int] = field(default_factory=dict)
    fn: dict[int, int] = field(default_factory=dict)
    iou: dict[int, float] = field(default_factory=dict)

    def update(self, pred_sem: np.ndarray, pred_inst: np.ndarray, gt_sem: np.ndarray, gt_inst: np.ndarray) -> None:
        """Add one image. Arrays [H, W]; instance 0 on a thing class is treated as its own segment id 0."""
        self.add(self.image(pred_sem, pred_inst, gt_sem, gt_inst))

    def add(self, other: PanopticAccumulator) -> None:
        """Add the counts of another accumulator (of the same classes)."""
        for mine, theirs in ((self.tp, other.tp), (self.fp, other.fp), (self.fn, other.fn), (self.iou, other.iou)):
            for c, v in theirs.items():
                mine[c] = mine.get(c, 0) + v

    def image(self, pred_sem: np.ndarray, pred_inst: np.ndarray, gt_sem: np.ndarray, gt_inst: np.ndarray
              ) -> PanopticAccumulator:
        """A new accumulator of the same classes holding one image's counts (self is not changed, so images
        can be counted on several threads and added in any order)."""
        one = PanopticAccumulator(self.things, self.stuff, self.void)
        one._count(pred_sem, pred_inst, gt_sem, gt_inst)
        return one

    def _count(self, pred_sem: np.ndarray, pred_inst: np.ndarray, gt_sem: np.ndarray, gt_inst: np.ndarray) -> None:
        if pred_sem.shape != gt_sem.shape or pred_inst.shape != gt_inst.shape or pred_sem.shape != pred_inst.shape:
            raise ValueError(f"panoptic shapes differ: pred {pred_sem.shape}/{pred_inst.shape}, "
                             f"gt {gt_sem.shape}/{gt_inst.shape}")
        classes = self.things | self.stuff
        p = _segments(pred_sem, pred_inst, self.things, classes).ravel()
        g = _segments(gt_sem, gt_inst, self.things, classes).ravel()
        gt_void = ~np.isin(gt_sem.ravel(), list(classes))
        p_ids, p_area = np.unique(p[p >= 0], return_counts=True)
        g_ids, g_area = np.unique(g[g >= 0], return_counts=True)
        p_void = {k: 0 for k in p_ids}
        pv, pv_n = np.unique(p[(p >= 0) & gt_void], return_counts=True)
        p_void.update(dict(zip(pv, pv_n)))
        both = (p >= 0) & (g >= 0)
        # (pred, gt) pairs as one int64 key (segment keys are below 2^28): a 1-D unique, in (pred, gt) order
        pair_keys, inter = np.unique(p[both] << 32 | g[both], return_counts=True)
        pa, ga = dict(zip(p_ids, p_area)), dict(zip(g_ids, g_area))
        matched_p, matched_g = set(), set()
        for pk, gk, n in zip(pair_keys >> 32, pair_keys & 0xFFFFFFFF, inter):
            if pk >> 20 != gk >> 20:
                continue
            union = pa[pk] + ga[gk] - n - p_void[pk]
            iou = n / union if union > 0 else 0.0
            if iou > 0.5:
                c = int(gk >> 20)
                matched_p.add(pk)
                matched_g.add(gk)
                self.tp[c] = self.tp.get(c, 0) + 1
                self.iou[c] = self.iou.get(c, 0.0) + float(iou)
        for gk in g_ids:
            if gk not in matched_g:
                c = int(gk >> 20)
                self.fn[c] = self.fn.get(c, 0) + 1
        for pk in p_ids:
            if pk not in matched_p and p_void[pk] / pa[pk] <= 0.5:
                c = int(pk >> 20)
                self.fp[c] = self.fp.get(c, 0) + 1

    def compute(self) -> dict[str, float]:
        """pq, sq, rq (all classes), pq_things, pq_stuff, and per-class pq_<id>; NaN where undefined."""
        out: dict[str, float] = {}
        per: dict[int, tuple[float, float, float]] = {}
        for c in sorted(self.things | self.stuff):
            tp, fp, fn = self.tp.get(c, 0), self.fp.get(c, 0), self.fn.get(c, 0)
            if tp + fp + fn == 0:
                continue
            iou = self.iou.get(c, 0.0)
            denom = tp + 0.5 * fp + 0.5 * fn
            per[c] = (iou / denom, iou / tp if tp else 0.0, tp / denom)
            out[f"pq_{c}"] = per[c][0]

        def mean(sel: Iterable[int], i: int) -> float:
            vals = [per[c][i] for c in sel if c in per]
            return float(np.mean(vals)) if vals else float("nan")

        out.update(pq=mean(per, 0), sq=mean(per, 1), rq=mean(per, 2),
                   pq_things=mean(self.things, 0), pq_stuff=mean(self.stuff, 0))
        return out


@dataclass
class ConfusionAccumulator:
    """Pixel confusion counts for mean IoU: rows = ground-truth class (void ignored), columns = predicted
    class, plus a last column for predictions outside the classes (e.g. void), which count as misses.

    IoU_c = M[c, c] / (sum_j M[c, j] + sum_i M[i, c] - M[c, c]); mIoU = mean over classes with a union.
    """

    n_classes: int
    matrix: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.matrix = np.zeros((self.n_classes, self.n_classes + 1), np.int64)

    def update(self, pred_sem: np.ndarray, gt_sem: np.ndarray) -> None:
        self.matrix += self.image(pred_sem, gt_sem)

    def image(self, pred_sem: np.ndarray, gt_sem: np.ndarray) -> np.ndarray:
        """One image's confusion counts [n_classes, n_classes + 1] (self is not changed)."""
        n = self.n_classes
        g = gt_sem.ravel().astype(np.int64)
        p = pred_sem.ravel().astype(np.int64)
        keep = (g >= 0) & (g < n)
        g, p = g[keep], p[keep]
        p = np.where((p >= 0) & (p < n), p, n)
        return np.bincount(g * (n + 1) + p, minlength=n * (n + 1)).reshape(n, n + 1)

    def iou_per_class(self) -> np.ndarray:
        """IoU per class; NaN for classes absent from both prediction and ground truth."""
        n = self.n_classes
        tp = np.diag(self.matrix[:, :n]).astype(np.float64)
        union = self.matrix.sum(1) + self.matrix[:, :n].sum(0) - tp
        return np.where(union > 0, tp / np.maximum(union, 1), np.nan)

    def miou(self) -> float:
        ious = self.iou_per_class()
        return float(np.nanmean(ious)) if np.isfinite(ious).any() else float("nan")


def dominant_ids(gt_inst: np.ndarray, pred_inst: np.ndarray, fruit_ids: Iterable[int],
                 min_share: float = 0.5, min_px: int = 1) -> dict[int, int]:
    """For each ground-truth fruit id showing at least `min_px` pixels: the predicted instance id covering
    more than `min_share` of its pixels (0 if none does, i.e. the fruit is split, missed or labelled stuff).
    Fruits with fewer pixels count as not visible in this frame."""
    out = {}
    for f in fruit_ids:
        px = pred_inst[gt_inst == f]
        if px.size < max(min_px, 1):
            continue
        ids, n = np.unique(px, return_counts=True)
        j = int(np.argmax(n))
        out[int(f)] = int(ids[j]) if ids[j] != 0 and n[j] > min_share * px.size else 0
    return out


def ids_by_fruit(per_frame: list[dict[int, int]]) -> tuple[dict[int, list[int]], dict[int, set[int]]]:
    """From per-frame {gt fruit id: dominant predicted id}: (the predicted ids each fruit carries, frame by
    frame; the fruits each non-zero predicted id covers)."""
    seen: dict[int, list[int]] = {}
    owners: dict[int, set[int]] = {}
    for frame in per_frame:
        for f, p in frame.items():
            seen.setdefault(f, []).append(p)
            if p:
                owners.setdefault(p, set()).add(f)
    return seen, owners


def id_consistency(per_frame: list[dict[int, int]], min_frames: int = 3) -> tuple[float, int]:
    """Share of fruits seen in >= min_frames frames that carry one single non-zero predicted id in all
    of them, that id belonging to no other fruit in any frame. `per_frame`: list over frames of
    {gt fruit id: dominant predicted id} (from `dominant_ids`). Returns (share, number of fruits scored).
    """
    seen, owners = ids_by_fruit(per_frame)
    scored = [f for f, ps in seen.items() if len(ps) >= min_frames]
    if not scored:
        return float("nan"), 0
    ok = sum(1 for f in scored if len(set(seen[f])) == 1 and seen[f][0] != 0 and owners[seen[f][0]] == {f})
    return ok / len(scored), len(scored)


def id_failures(per_frame: list[dict[int, int]], min_frames: int = 3) -> dict[str, int]:
    """Why the fruits that `id_consistency` scores fail it, as counts of fruits per kind (a fruit can fail in
    several ways): 'unlabelled' = in some frame no predicted id covers most of it (missed, split inside the
    frame, or painted as stuff); 'split' = it carries two or more non-zero ids over its frames; 'shared' = an
    id it carries is another fruit's in some frame; 'one_frame' = it would pass without one of its frames
    (every other frame carries one id that no other fruit carries). Input as for `id_consistency`."""
    seen, owners = ids_by_fruit(per_frame)
    out = {"unlabelled": 0, "split": 0, "shared": 0, "one_frame": 0}
    for f, ps in seen.items():
        nonzero = set(ps) - {0}
        if len(ps) < min_frames or (len(set(ps)) == 1 and ps[0] != 0 and owners[ps[0]] == {f}):
            continue
        out["unlabelled"] += 0 in ps
        out["split"] += len(nonzero) > 1
        out["shared"] += any(owners[p] != {f} for p in nonzero)
        counts = {p: ps.count(p) for p in set(ps)}
        top = max(counts, key=counts.get)
        out["one_frame"] += bool(top and counts[top] == len(ps) - 1 and owners[top] == {f})
    return out
