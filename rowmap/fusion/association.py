"""Association: window slots -> local fruits (a slot's pixel groups that lie together) -> row fruits (local fruits
of different windows with close centres and overlapping masks: Hungarian per window pair, then union-find)."""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from functools import cached_property
from itertools import combinations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components

from nerf.config import BASE_PIXELS
from nerf.surfaces import fruit_sphere, robust_centre, runs_by_key, unproject
from rowmap.fusion.settings import Config
from rowmap.geometry import pixel_groups, sphere_behind, subsample

MAX_GROUPS = 256
"""pixel groups one slot can split into in one frame (further groups stay with the largest)."""
MIN_GROUP_PX = 50
"""pixels at 320x180 (scaled by area): a smaller group stays with its slot's largest."""
MIN_SLOT_PX = 4
"""pixels over all frames: a smaller slot is dropped (its pixels become void)."""
MAX_POINTS = 400
"""points kept per slot group and frame (evenly subsampled)."""
MIN_SPLIT_FRAMES = 2
"""frames: a cluster of a slot's (or a fruit's detector) centres seen in fewer is no fruit of its own."""
MIN_SPHERE_POINTS = 20
"""points: fewer fit no sphere."""


def min_group_px(shape: tuple[int, ...]) -> int:
    """MIN_GROUP_PX for images of `shape` (H, W, ...): the same share at every size, (720, 1280) -> 800."""
    return int(round(MIN_GROUP_PX * max(1.0, shape[0] * shape[1] / BASE_PIXELS)))


def code(slot, group):
    """One number for a slot's pixel group in a frame (ints or int arrays)."""
    return slot * MAX_GROUPS + group


@dataclass
class SlotView:
    """One pixel group of one slot of one window in one rendered frame."""

    n_px: int
    class_px: np.ndarray   # [n_classes] pixel counts per class
    points: np.ndarray     # [n, 3] rendered world points (subsampled)
    eye: np.ndarray        # [3] camera centre
    sensor_offset: np.ndarray | None = None   # [3] median sensor point - rendered point; None: no sensor depth


@dataclass
class LocalFruit:
    """A window-local fruit: the (frame, group) views of one slot of one window that lie together."""

    window_id: int
    slot: int
    part: int
    frames: list[tuple[int, int]]
    n_px: int
    class_id: int
    centre: np.ndarray | None
    fruit_id: int = 0
    drop_reason: str = ""
    median: np.ndarray | None = None

    @cached_property
    def codes(self) -> dict[int, set[int]]:
        """frame -> the slot codes of this fruit's pixel groups there."""
        return frame_codes([self])


def frame_codes(lfs: list[LocalFruit]) -> dict[int, set[int]]:
    """frame -> the slot codes of the local fruits' pixel groups there."""
    out: dict[int, set[int]] = defaultdict(set)
    for lf in lfs:
        for f, g in lf.frames:
            out[f].add(int(code(lf.slot, g)))
    return dict(out)


def slot_views(sem: np.ndarray, inst: np.ndarray, depth: np.ndarray, sensor: np.ndarray, k: np.ndarray,
               c2w: np.ndarray, thing_ids: list[int], cfg: Config) -> tuple[dict, np.ndarray]:
    """One rendered frame's slot views ({(slot, group): SlotView}) and slot-code map [H, W] (0 = no slot; uint16
    where the codes fit: a row holds every frame's map). `sensor`: the recorded z-depth in m (0 = none)."""
    thing = np.isin(sem, thing_ids) & (inst > 0)
    group, out = np.zeros(inst.shape, np.int32), {}
    v, u, ids, starts, ends = runs_by_key(*np.nonzero(thing), inst[thing])
    min_px = min_group_px(inst.shape)
    for s0, s1 in zip(starts, ends):
        vv, uu = v[s0:s1], u[s0:s1]
        good = depth[vv, uu] > 0
        pts = unproject(depth, k, c2w, vv[good], uu[good])
        labels = np.zeros(len(vv), np.int64)
        labels[good] = pixel_groups(vv[good], uu[good], pts, cfg.group_gap_m, min_px, MAX_GROUPS)
        group[vv, uu] = labels
        for g in range(int(labels.max()) + 1):
            mine = labels == g
            pts_g = pts[labels[good] == g]
            offset, both = None, mine & good & (sensor[vv, uu] > 0)
            if both.any():
                sel = subsample(int(both.sum()), MAX_POINTS)
                vb, ub = vv[both][sel], uu[both][sel]
                offset = np.median(unproject(sensor, k, c2w, vb, ub) - unproject(depth, k, c2w, vb, ub), 0)
            cls = np.bincount(sem[vv[mine], uu[mine]], minlength=max(thing_ids) + 1)
            out[(int(ids[s0]), g)] = SlotView(int(mine.sum()), cls, pts_g[subsample(len(pts_g), MAX_POINTS)],
                                              c2w[:3, 3], offset)
    codes = np.where(thing, code(inst.astype(np.int64), group), 0)
    return out, codes.astype(np.uint16 if codes.max(initial=0) <= np.iinfo(np.uint16).max else np.int32)


def split_frames(frame_centres: dict, dist_m: float, min_frames: int = 1) -> list[list]:
    """Single-linkage clusters (closer than dist_m) of per-frame centres keyed by (frame, group); keys without
    a centre, and clusters of fewer than min_frames keys, join the largest cluster."""
    keys = [f for f, c in frame_centres.items() if c is not None]
    rest = [f for f, c in frame_centres.items() if c is None]
    if dist_m <= 0 or len(keys) < 2:
        return [sorted(keys + rest)]
    pts = np.stack([frame_centres[f] for f in keys])
    _, lab = connected_components(np.linalg.norm(pts[:, None] - pts[None], axis=2) <= dist_m, directed=False)
    groups = sorted((sorted(f for f, g in zip(keys, lab) if g == c) for c in set(lab)), key=lambda g: (-len(g), g[0]))
    small = [f for g in groups[1:] if len(g) < min_frames for f in g]
    return [sorted(groups[0] + rest + small)] + [g for g in groups[1:] if len(g) >= min_frames]


def local_fruits(views: dict[tuple[int, int], dict], cfg: Config) -> list[LocalFruit]:
    """Local fruits of every window's slots (`views`: (window, slot) -> {(frame, group): SlotView}), centred on
    their fitted sphere, else one of the row's median radius behind the seen cap, else their points' median."""
    local, unfitted, radii = [], [], []
    for (wid, slot), per_frame in sorted(views.items()):
        centres = {f: (np.median(sv.points, 0) if len(sv.points) else None) for f, sv in per_frame.items()}
        for p, keys in enumerate(split_frames(centres, 2 * cfg.max_match_distance_m, MIN_SPLIT_FRAMES)):
            svs = [per_frame[f] for f in keys]
            n_px = sum(sv.n_px for sv in svs)
            pts = np.concatenate([sv.points for sv in svs])
            lf = LocalFruit(wid, slot, p, keys, n_px, int(np.argmax(sum(sv.class_px for sv in svs))), None)
            if n_px < MIN_SLOT_PX:
                lf.drop_reason = f"{n_px} px < {MIN_SLOT_PX}"
            elif len(pts) == 0:
                lf.drop_reason = "no pixel with valid rendered depth"
            elif (fit := fruit_sphere(pts, cfg.max_fruit_radius_m, min_points=MIN_SPHERE_POINTS)) is not None:
                lf.centre, lf.median = fit[0], fit[2]
                radii.append(fit[1])
            else:
                lf.centre = lf.median = robust_centre(pts)[0]
                unfitted.append((lf, pts, np.average([sv.eye for sv in svs], 0, [len(sv.points) + 1e-9 for sv in svs])))
            local.append(lf)
    for lf, pts, eye in unfitted if radii else []:
        c = sphere_behind(pts, eye, float(np.median(radii)), min_points=MIN_SPHERE_POINTS)
        lf.centre = lf.centre if c is None else c
    return local


def centre_distance(a: LocalFruit, b: LocalFruit) -> float:
    """The smaller of the distances of two local fruits' centres and of their medians (m)."""
    d = float(np.linalg.norm(a.centre - b.centre))
    return d if a.median is None or b.median is None else min(d, float(np.linalg.norm(a.median - b.median)))


class MaskOverlaps:
    """The slot-code maps of frames several windows rendered ({(window, frame): [H, W]}) as pairwise histograms."""

    def __init__(self, masks: dict[tuple[int, int], np.ndarray]):
        self.masks, self._joint = masks, {}
        self.shared: dict[tuple[int, int], list[int]] = defaultdict(list)   # window pair -> frames both rendered
        for f in sorted({f for _, f in masks}):
            for pair in combinations(sorted(w for w, g in masks if g == f), 2):
                self.shared[pair].append(f)

    def joint(self, wa: int, wb: int, f: int) -> list[tuple[int, int, int]]:
        """(code in wa, code in wb, pixels) over frame f's pixels where either window has a slot."""
        lo, hi = min(wa, wb), max(wa, wb)
        if (lo, hi, f) not in self._joint:
            a, b = self.masks[(lo, f)].ravel(), self.masks[(hi, f)].ravel()
            on = (a != 0) | (b != 0)
            keys, n = np.unique((a[on].astype(np.int64) << 32) | b[on].astype(np.int64), return_counts=True)
            self._joint[(lo, hi, f)] = list(zip((keys >> 32).tolist(), (keys & 0xFFFFFFFF).tolist(), n.tolist()))
        out = self._joint[(lo, hi, f)]
        return out if wa == lo else [(y, x, n) for x, y, n in out]

    def overlap(self, wa: int, codes_a: dict, wb: int, codes_b: dict) -> tuple[int, int]:
        """(intersection, union) pixels of two windows' masks ({frame: codes}) over the frames both rendered and
        both masks hold: a window that does not paint the fruit in a frame says nothing of the other's mask."""
        inter = union = 0
        for f in self.shared.get((min(wa, wb), max(wa, wb)), []):
            if f not in codes_a or f not in codes_b:
                continue
            ca, cb = codes_a[f], codes_b[f]
            for x, y, n in self.joint(wa, wb, f):
                union += n * (x in ca or y in cb)
                inter += n * (x in ca and y in cb)
        return inter, union

    def under(self, lf: LocalFruit, owner: dict[tuple[int, int, int], int]) -> tuple[dict[int, int], int]:
        """({k: pixels of lf's mask that lie on local fruit k's mask}, pixels of lf's mask) over the frames other
        windows rendered too; `owner`: (window, frame, slot code) -> local fruit index."""
        on, total = defaultdict(int), 0
        for (wa, wb), fids in self.shared.items():
            if lf.window_id not in (wa, wb):
                continue
            other = wb if lf.window_id == wa else wa
            for f in (f for f in fids if f in lf.codes):
                for own, theirs, n in self.joint(lf.window_id, other, f):
                    if own in lf.codes[f]:
                        total += n
                        if (k := owner.get((other, f, theirs))) is not None:
                            on[k] += n
        return on, total


MAX_PAIR_COST = 1.5
"""the largest pair_cost of a match: that of two centres max_match_distance_m apart without a shared frame."""
MAX_PAIR_REACH = 4.0
"""multiple of max_match_distance_m: two windows' slots farther apart are never one fruit, whatever their masks."""


def pair_cost(a: LocalFruit, b: LocalFruit, overlaps: MaskOverlaps, cfg: Config) -> float:
    """The cost of two windows' local fruits being one, d = centre distance / max_match_distance_m: (1 - mask IoU)
    x (1 + d) on frames both show, 0.5 + d without; inf over MAX_PAIR_COST, past MAX_PAIR_REACH or under min_mask_iou.
    Where masks agree, distance matters little: a window that saw a fruit at its image border can place it cm off."""
    dist = centre_distance(a, b)
    if dist > MAX_PAIR_REACH * cfg.max_match_distance_m:
        return np.inf
    inter, union = overlaps.overlap(a.window_id, a.codes, b.window_id, b.codes)
    d = dist / cfg.max_match_distance_m
    if union and inter / union < cfg.min_mask_iou:
        return np.inf
    cost = (1.0 - inter / union) * (1.0 + d) if union else 0.5 + d
    return cost if cost <= MAX_PAIR_COST else np.inf


def candidate_pairs(fruits: list[LocalFruit], overlaps: MaskOverlaps, cfg: Config) -> list[tuple[float, int, int]]:
    """(cost, i, j) of the Hungarian matches (pair_cost) of every pair of windows."""
    by_window: dict[int, list[int]] = defaultdict(list)
    for i, lf in enumerate(fruits):
        if lf.centre is not None:
            by_window[lf.window_id].append(i)
    edges = []
    for wa, wb in combinations(sorted(by_window), 2):
        ia, ib = by_window[wa], by_window[wb]
        ca, cb = np.stack([fruits[i].centre for i in ia]), np.stack([fruits[j].centre for j in ib])
        near = np.linalg.norm(ca[:, None] - cb[None], axis=2) <= MAX_PAIR_REACH * cfg.max_match_distance_m
        cost = np.full(near.shape, np.inf)
        for r, c in zip(*np.nonzero(near)):
            cost[r, c] = pair_cost(fruits[ia[r]], fruits[ib[c]], overlaps, cfg)
        finite = np.isfinite(cost)
        if finite.any():
            rows, cols = linear_sum_assignment(np.where(finite, cost, 1e6))
            edges += [(float(cost[r, c]), ia[r], ib[c]) for r, c in zip(rows, cols) if finite[r, c]]
    return edges


def associate(fruits: list[LocalFruit], masks: dict[tuple[int, int], np.ndarray], cfg: Config) -> list[list[int]]:
    """Groups of local-fruit indices that are one row fruit: candidate_pairs merged cheapest first while every two
    windows' masks overlap by min_mask_iou on the frames both rendered. A fruit left alone whose mask lies mostly
    on one group's, its sphere centre within max_match_distance_m of one of theirs, joins it: a second slot its
    window painted on that fruit (centres only, not medians: this join checks no masks)."""
    overlaps = MaskOverlaps(masks)
    members = {i: [i] for i in range(len(fruits))}
    root = list(range(len(fruits)))

    def compatible(a: list[int], b: list[int]) -> bool:
        by_w: dict[int, list[LocalFruit]] = defaultdict(list)
        for i in a + b:
            by_w[fruits[i].window_id].append(fruits[i])
        for wa, wb in combinations(sorted(by_w), 2):
            inter, union = overlaps.overlap(wa, frame_codes(by_w[wa]), wb, frame_codes(by_w[wb]))
            if union and inter / union < cfg.min_mask_iou:
                return False
        return True

    def join(ra: int, rb: int) -> None:
        for i in members[rb]:
            root[i] = ra
        members[ra] += members.pop(rb)

    for _, i, j in sorted(candidate_pairs(fruits, overlaps, cfg)):
        if root[i] != root[j] and compatible(members[root[i]], members[root[j]]):
            join(root[i], root[j])
    owner = {(lf.window_id, f, c): k for k, lf in enumerate(fruits) if lf.centre is not None
             for f, cs in lf.codes.items() for c in cs}
    for i, lf in enumerate(fruits):
        if lf.centre is None or len(members.get(i, ())) != 1:
            continue
        under, total = overlaps.under(lf, owner)
        on = defaultdict(int)     # group root -> pixels of this fruit's mask on its masks
        for k, n in under.items():
            on[root[k]] += n
        if on:
            r, n_on = max(on.items(), key=lambda kv: kv[1])
            gap = min(float(np.linalg.norm(lf.centre - fruits[k].centre)) for k in members[r])
            if n_on >= total / 2 and gap <= cfg.max_match_distance_m:
                join(r, i)
    return [g for g in members.values() if fruits[g[0]].centre is not None]   # a fruit without a centre stays alone


def row_fruits(views: dict[tuple[int, int], dict], masks: dict[tuple[int, int], np.ndarray], cfg: Config
               ) -> tuple[list[LocalFruit], list[list[int]]]:
    """Local fruits and their groups that are one row fruit, each given its fruit's id (along the row: x, z, y)."""
    local = local_fruits(views, cfg)
    groups = associate(local, masks, cfg)
    centre = [np.median(np.stack([local[i].centre for i in g]), 0) for g in groups]
    order = sorted(range(len(groups)), key=lambda j: (centre[j][0], centre[j][2], centre[j][1]))
    for fruit_id, j in enumerate(order, 1):
        for i in groups[j]:
            local[i].fruit_id = fruit_id
    return local, groups


def slot_table(local: list[LocalFruit]) -> dict[tuple[int, int], dict[int, int]]:
    """{(window, frame): {slot code: fruit id}}: how each render's slots map to row fruits."""
    lut: dict[tuple[int, int], dict[int, int]] = defaultdict(dict)
    for lf in local:
        for f, cs in lf.codes.items():
            lut[(lf.window_id, f)].update(dict.fromkeys(cs, lf.fruit_id))
    return lut
