"""Rounds: assign every frame, refit the fruit models from what they were given, assign again. Frames are
independent within a round (the models change only between rounds), so several threads work on them; results
come back in frame order, so the output does not depend on the thread count."""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from nerf.surfaces import robust_centre
from pipeline.parallel import available_cores, in_order
from rowmap.fusion.assignment import assign
from rowmap.fusion.association import MAX_POINTS, min_group_px
from rowmap.fusion.evidence import Frame, frame_evidence
from rowmap.fusion.models import FruitModels, update
from rowmap.fusion.settings import Config
from rowmap.geometry import subsample


def fused_label(frame: Frame, models: FruitModels, owners: dict, cfg: Config) -> tuple[np.ndarray, object, np.ndarray]:
    """([H, W] fused fruit ids of one frame, 0 = background, -1 = void where the render had a dropped slot and
    the pixel stays background; the evidence; the assigned id of each evidence pixel)."""
    ev = frame_evidence(frame, models, owners, cfg)
    ids = assign(ev, cfg)
    out = frame.label.copy()
    was = out.ravel()[ev.pixels]
    out.ravel()[ev.pixels] = np.where((ids == 0) & (was < 0), -1, ids)
    return out, ev, ids


def round_views(frame: Frame, models: FruitModels, owners: dict, cfg: Config) -> tuple[list, list]:
    """What one frame of a round gives the refit: [(fruit, its pixels' points)] and [(fruit, (frame, segment,
    pixels, centre [3], points))] of the detector segments lying mostly on fruits, each given to the fruit
    holding most of it (at least min_group_px of its pixels)."""
    _, ev, ids = fused_label(frame, models, owners, cfg)
    grown, segs, taken = [], [], set()
    for f in np.unique(ids[ids > 0]):
        pts = ev.points[ids == f]
        grown.append((int(f), pts[subsample(len(pts), MAX_POINTS)]))
    if cfg.detector_split_m <= 0:
        return grown, segs
    on = (ids > 0) & (ev.segment > 0)
    size = np.bincount(ev.segment, minlength=1)
    covered = np.bincount(ev.segment[on], minlength=len(size))
    keys, inverse, n = np.unique(ids[on] * len(size) + ev.segment[on], return_inverse=True, return_counts=True)
    min_px = min_group_px(frame.label.shape)
    for j in np.argsort(-n, kind="stable"):
        f, s = divmod(int(keys[j]), len(size))
        if n[j] >= min_px and 2 * covered[s] > size[s] and s not in taken:
            taken.add(s)
            pts = ev.points[on][inverse == j]
            segs.append((f, (frame.frame_id, s, int(n[j]), robust_centre(pts)[0], pts[:: max(1, len(pts) // 400)])))
    return grown, segs


def fuse(frame_ids: Iterable[int], load: Callable[[int], Frame], models: FruitModels, cfg: Config,
         progress: Callable = lambda it, label, total: it, threads: int = 0,
         load_last: Callable[[int], Frame] | None = None) -> Iterator[tuple[int, np.ndarray, FruitModels]]:
    """(frame id, fused label [H, W], the final models) per frame of the last round, in frame order. Each round
    before it collects, per fruit, the points of the pixels it was given and its detector segments
    (round_views), and refits the models with them (rowmap.fusion.models.update). `threads`: frames worked on
    at once (0 = every core of this process); `load` must be safe to call from several threads. `load_last`
    (default `load`) loads the frames of the last round: a caller that keeps what it writes with each frame
    keeps it only there, a few frames ahead of the writes, not for every frame of the earlier rounds."""
    frame_ids, owners, threads = list(frame_ids), {}, threads or available_cores()
    for r in range(cfg.refine_rounds):
        grown: dict[int, list[np.ndarray]] = defaultdict(list)
        seg_views: dict[int, list[tuple]] = defaultdict(list)
        views = in_order(lambda fid: round_views(load(fid), models, owners, cfg), frame_ids, threads)
        for points, segs in progress(views, f"fusion round {r + 1}", len(frame_ids)):
            for f, pts in points:
                grown[f].append(pts)
            for f, view in segs:
                seg_views[f].append(view)
        models, owners = update(models, grown, seg_views, cfg)
    last = load_last or load
    fused = in_order(lambda fid: (fid, fused_label(last(fid), models, owners, cfg)[0]), frame_ids, threads)
    for fid, out in progress(fused, "write fused frames", len(frame_ids)):
        yield fid, out, models
