"""Rounds: assign every frame, refit the fruit models from what they were given, assign again; the last
round's assignment is the fused frame (written once, by the caller)."""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from rowmap.fusion.assignment import assign
from rowmap.fusion.evidence import Frame, frame_evidence
from rowmap.fusion.models import FruitModels, segment_views, update
from rowmap.fusion.association import MIN_GROUP_PX, MAX_POINTS
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


def fuse(frame_ids: Iterable[int], load: Callable[[int], Frame], models: FruitModels, cfg: Config,
         progress: Callable = lambda it, label, total: it) -> Iterator[tuple[int, np.ndarray, FruitModels]]:
    """(frame id, fused label [H, W], the final models) per frame of the last round. Each round before it
    collects, per fruit, the points of the pixels it was given (MAX_POINTS per frame) and its detector segments
    (segment_views), and refits the models with them (rowmap.fusion.models.update)."""
    frame_ids, owners = list(frame_ids), {}
    for r in range(cfg.refine_rounds):
        grown: dict[int, list[np.ndarray]] = defaultdict(list)
        seg_views: dict[int, list[tuple]] = defaultdict(list)
        for fid in progress(frame_ids, f"fusion round {r + 1}", len(frame_ids)):
            frame = load(fid)
            _, ev, ids = fused_label(frame, models, owners, cfg)
            order = np.argsort(ids, kind="stable")
            starts = np.flatnonzero(np.r_[True, ids[order][1:] != ids[order][:-1]]) if len(ids) else []
            for s0, s1 in zip(starts, np.r_[starts[1:], len(ids)] if len(ids) else []):
                f = int(ids[order[s0]])
                if f > 0:
                    grown[f].append(ev.points[order[s0:s1][subsample(s1 - s0, MAX_POINTS)]])
            if frame.segments is not None and cfg.detector_split_m > 0:
                for f, *view in segment_views(ids, ev.segment, ev.points, MIN_GROUP_PX):
                    seg_views[f].append((fid, *view))
        models, owners = update(models, grown, seg_views, cfg)
    for fid in progress(frame_ids, "write fused frames", len(frame_ids)):
        out, _, _ = fused_label(load(fid), models, owners, cfg)
        yield fid, out, models
