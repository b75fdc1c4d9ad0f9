"""One assignment per frame, in rounds. Each pixel takes the option (background or a fruit) of least cost,

    cost[p, o] = sum over terms t of WEIGHTS[t] * term_t[p, o]        (each term in [0, 1])

then the models are refitted from what they were given and every frame is assigned again. The models change
only between rounds, so a round's frames run in threads; they come back in frame order, whatever the count."""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from nerf.config import BASE_PIXELS
from nerf.surfaces import robust_centre, runs_by_key
from pipeline.parallel import available_cores, in_order
from rowmap.fusion.association import MAX_POINTS, min_group_px
from rowmap.fusion.evidence import Evidence, Frame, pixel_evidence
from rowmap.fusion.models import FruitModels, SegmentView, update
from rowmap.fusion.settings import Config
from rowmap.geometry import subsample

WEIGHTS = {"render": 1.0, "detector": 0.8, "shape": 1.5, "surface": 0.6, "order": 1.5}
"""the weight of each term in the cost (render 1 sets the scale)."""
OTHER_FRUIT = 0.5
"""detector term of a fruit a segment does not name, on its pixels (background pays 1): a segment says more surely
that some fruit lies there than which one (it can merge two fruits and is named for the one painted most)."""
SHAPE_INSIDE = 0.2
"""shape cost of background on a point inside a fruit's sphere, on the half facing the camera."""
UNKNOWN_SHAPE = 0.8
"""shape cost of a fruit without a sphere that the render or the detector names, on a point inside another
fruit's sphere (0 on a point in none; 1 where nothing names it: it has no extent to claim a pixel by). With the
weights, between render and render + SHAPE_INSIDE: that fruit takes the pixel, background does not."""
TILE_PX = 64
"""pixels of a 320x180 image (scaled with the image): the side of the square tiles a frame is assigned in."""
FAR_LOSES = WEIGHTS["shape"] * (1 - SHAPE_INSIDE) > WEIGHTS["detector"]
"""whether a candidate outside its halo ball always costs more than background (what `tiles` needs)."""


def terms(ev: Evidence, cfg: Config) -> dict[str, np.ndarray]:
    """Each term of the cost, [P, F + 1] (column 0 = background)."""
    n, cols = len(ev.pixels), np.arange(len(ev.ids) + 1)[None]
    doubt = np.where((ev.render[:, None] == 0) & (cols > 0), 1 - ev.fruit[:, None], 1.0)   # of a background call
    out = {"render": ev.confidence[:, None] * (cols != ev.render[:, None]) * doubt}
    seg_fruit, unnamed = ev.detector[:, None], np.where(cols == 0, 1.0, OTHER_FRUIT)   # [P, 1], [1, F + 1]
    det = np.where(seg_fruit > 0, np.where(cols == seg_fruit, 0.0, unnamed), cols == 0)
    out["detector"] = (ev.detector >= 0)[:, None] * det
    r = ev.radius[None]
    excess = (ev.rel - 1.0 - cfg.margin_m / r) / (cfg.halo_factor - 1.0 + 1e-9)   # radii beyond radius + margin
    front = ~(ev.beyond > cfg.margin_m)
    inside = ((ev.rel <= 1.0 + cfg.margin_m / r) & front).any(1)
    named = (cols[:, 1:] == ev.render[:, None]) | (cols[:, 1:] == ev.detector[:, None])
    unknown = np.where(named, UNKNOWN_SHAPE * inside[:, None], 1.0)
    out["shape"] = np.c_[SHAPE_INSIDE * inside, np.where(np.isnan(ev.rel), unknown, np.clip(excess, 0.0, 1.0))]
    on = np.isfinite(ev.gap) & front
    surface = np.minimum(np.where(on, ev.gap, np.inf) / cfg.margin_m, 1.0)
    out["surface"] = np.c_[np.ones(n), surface] * on.any(1)[:, None]
    out["order"] = np.c_[np.zeros(n), np.nan_to_num(np.clip((ev.beyond - cfg.margin_m) / r, 0.0, 1.0))]
    return out


def cost(ev: Evidence, cfg: Config) -> np.ndarray:
    """[P, F + 1] the weighted sum of the terms not in cfg.terms_off."""
    total = np.zeros((len(ev.pixels), len(ev.ids) + 1))
    for name, term in terms(ev, cfg).items():
        if name not in cfg.terms_off:
            total += WEIGHTS[name] * term
    return total


def tiles(ev: Evidence, shape: tuple[int, int], cfg: Config) -> Iterator[tuple]:
    """(rows, cols) per square tile: its evidence pixels and the candidates that can win one: those whose halo box
    meets the tile, or that the render or the detector names there. Any other lies outside its halo ball or has
    no sphere, so it costs more than background (FAR_LOSES): the tiles give the ids every pixel against every
    candidate gives. One tile with shape off."""
    h, w = shape
    if "shape" in cfg.terms_off or not FAR_LOSES or not len(ev.pixels):
        yield np.arange(len(ev.pixels)), np.arange(len(ev.ids))
        return
    side = int(np.ceil(TILE_PX * np.sqrt(max(1.0, h * w / BASE_PIXELS))))
    per_row = -(-w // side)
    v, u = np.divmod(ev.pixels, w)
    tile = (v // side) * per_row + u // side
    col = {int(f): j for j, f in enumerate(ev.ids)}
    boxes = [(col[f], b) for f, b in (ev.boxes or {}).items() if f in col]
    order = np.argsort(tile, kind="stable")
    keys, starts = np.unique(tile[order], return_index=True)
    for t, rows in zip(keys, np.split(order, starts[1:])):
        v0, u0 = (t // per_row) * side, (t % per_row) * side
        near = [j for j, (b0, b1, c0, c1) in boxes if b0 < v0 + side and v0 < b1 and c0 < u0 + side and u0 < c1]
        named = np.r_[ev.render[rows], ev.detector[rows]]
        yield rows, np.unique(np.r_[near, named[named > 0] - 1].astype(np.int64))


def fused_label(frame: Frame, models: FruitModels, owners: dict, cfg: Config
                ) -> tuple[np.ndarray, Evidence, np.ndarray]:
    """One frame's fused ids [H, W] (-1: a dropped slot left background), its evidence, and its pixels' ids [P]."""
    ev = pixel_evidence(frame, models, owners, cfg)
    ids = np.zeros(len(ev.pixels), np.int64)
    for rows, cols in tiles(ev, frame.label.shape, cfg):
        part = ev.part(rows, cols, models, frame.c2w[:3, 3], cfg)
        c = cost(part, cfg)
        c[np.arange(len(c)), part.render] -= 1e-6   # ties go to the render's option
        ids[rows] = np.r_[0, part.ids][c.argmin(1)]
    out = frame.label.copy()
    out.ravel()[ev.pixels] = np.where((ids == 0) & (out.ravel()[ev.pixels] < 0), -1, ids)
    return out, ev, ids


def round_views(frame: Frame, models: FruitModels, owners: dict, cfg: Config) -> tuple[list, list]:
    """What one frame gives the refit: [(fruit, its pixels' points)] and [(fruit, SegmentView)] of the detector
    segments lying mostly on fruits, each to the fruit holding most."""
    _, ev, ids = fused_label(frame, models, owners, cfg)
    given, segs, taken = [], [], set()
    fruit_px = np.flatnonzero(ids > 0)
    rows, _, fruit, starts, ends = runs_by_key(fruit_px, fruit_px, ids[fruit_px])   # evidence rows per fruit
    for f, s0, s1 in zip(fruit[starts], starts, ends):
        pts = ev.points[rows[s0:s1]]
        given.append((int(f), pts[subsample(len(pts), MAX_POINTS)]))
    if cfg.detector_split_m <= 0:
        return given, segs
    on = np.flatnonzero((ids > 0) & (ev.segment > 0))
    size = np.bincount(ev.segment, minlength=1)
    covered = np.bincount(ev.segment[on], minlength=len(size))
    rows, _, key, starts, ends = runs_by_key(on, on, ids[on] * len(size) + ev.segment[on])   # per (fruit, segment)
    min_px = min_group_px(frame.label.shape)
    for j in np.argsort(starts - ends, kind="stable"):   # most pixels first
        f, s = divmod(int(key[starts[j]]), len(size))
        n = int(ends[j] - starts[j])
        if n >= min_px and 2 * covered[s] > size[s] and s not in taken:
            taken.add(s)
            pts = ev.points[rows[starts[j]:ends[j]]]
            segs.append((f, SegmentView(frame.frame_id, s, n, robust_centre(pts)[0], pts[:: max(1, len(pts) // 400)],
                                        frame.c2w[:3, 3])))
    return given, segs


def fuse(frame_ids: Iterable[int], load: Callable[[int], Frame], models: FruitModels, cfg: Config,
         progress: Callable = lambda it, label, total: it, threads: int = 0
         ) -> tuple[FruitModels, Iterator[tuple[int, np.ndarray]]]:
    """The models after `refine_rounds` rounds (run here), and (frame id, fused label [H, W]) per frame in frame
    order, assigned as the iterator is read. `threads`: frames at once (0 = every core); `load`: thread-safe."""
    frame_ids, owners, threads = list(frame_ids), {}, threads or available_cores()
    for r in range(cfg.refine_rounds):
        given: dict[int, list[np.ndarray]] = defaultdict(list)
        seg_views: dict[int, list[SegmentView]] = defaultdict(list)
        views = in_order(lambda fid: round_views(load(fid), models, owners, cfg), frame_ids, threads)
        for points, segs in progress(views, f"fusion round {r + 1}", len(frame_ids)):
            for f, pts in points:
                given[f].append(pts)
            for f, view in segs:
                seg_views[f].append(view)
        models, owners = update(models, given, seg_views, cfg)
    fused = in_order(lambda fid: (fid, fused_label(load(fid), models, owners, cfg)[0]), frame_ids, threads)
    return models, progress(fused, "write fused frames", len(frame_ids))
