"""Fruit models, per row fruit its sphere and seen surface: built by `fit_models` from the association, asked by
the evidence through `FruitModels.query`, refitted by `update` after a round."""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, replace
from itertools import combinations
from typing import NamedTuple

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial import cKDTree

from nerf.panoptic.complete import sphere_boxes
from nerf.surfaces import fruit_sphere
from rowmap.fusion.association import MIN_SPHERE_POINTS, MIN_SPLIT_FRAMES, LocalFruit
from rowmap.fusion.settings import Config
from rowmap.geometry import sphere_behind, subsample

MAX_FIT_POINTS = 3000
"""points a sphere is fitted to (evenly subsampled)."""
TWO_FRUITS_APART = 1.5
"""multiple of the row's typical radius: two clusters of a fruit's detector segments seen in one frame farther
apart are two fruits (a leaf cuts one fruit into pieces at most about 1.3 radii apart)."""


class SegmentView(NamedTuple):
    """One detector segment lying mostly on one fruit in one frame (assignment.round_views)."""

    frame: int
    segment: int
    n_px: int             # its pixels on the fruit
    centre: np.ndarray    # [3] robust centre of its points
    points: np.ndarray    # [N, 3] world points (subsampled)
    eye: np.ndarray       # [3] camera centre


@dataclass
class FruitModel:
    """One row fruit: its seen surface points (where the sensor measures them) and the sphere they fit."""

    class_id: int
    points: np.ndarray                 # [N, 3] seen surface points
    centre: np.ndarray | None = None   # [3] sphere centre; None: no plausible sphere
    radius: float = np.nan
    surface: cKDTree | None = None     # the points inside the sphere, one per margin_m / 2 cube

    def refit(self, cfg: Config, behind: tuple[np.ndarray, float] | None = None) -> "FruitModel":
        """Fit the sphere to the points (keeping the old one where none fits), the seen surface to those inside it.
        `behind` (camera centre [3], radius m): where the free fit fails (a shallow cap), that sphere behind it."""
        fit = None
        if len(self.points) >= MIN_SPHERE_POINTS:
            pts = self.points[subsample(len(self.points), MAX_FIT_POINTS)]
            fit = fruit_sphere(pts, cfg.max_fruit_radius_m)
            if fit is None and behind is not None and behind[1] > 0:
                c = sphere_behind(pts, behind[0], behind[1], min_points=MIN_SPHERE_POINTS)
                fit = None if c is None else (c, behind[1])
        if fit is not None:
            self.centre, self.radius = fit[0], float(fit[1])
        if self.centre is not None:
            pts = self.points[np.linalg.norm(self.points - self.centre, axis=1) <= self.radius]
            pts = pts[np.unique(np.floor(pts / (cfg.margin_m / 2)).astype(np.int64), axis=0, return_index=True)[1]]
            self.surface = cKDTree(pts) if len(pts) else None
        return self


def dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[P, F] dot products of a [P, 3] and b [F, 3], elementwise (a BLAS matmul of this shape is slower)."""
    return a[:, :1] * b[:, 0] + a[:, 1:2] * b[:, 1] + a[:, 2:3] * b[:, 2]


class FruitModels(dict):
    """{fruit id: FruitModel}, with the queries one frame's evidence needs."""

    @property
    def typical_radius(self) -> float:
        """m: the median radius of the fruits' spheres (nan: no fruit has one)."""
        radii = [m.radius for m in self.values() if m.centre is not None]
        return float(np.median(radii)) if radii else np.nan

    def in_view(self, hw: tuple[int, int], k: np.ndarray, c2w: np.ndarray, cfg: Config) -> dict[int, tuple]:
        """{fruit id: image box (v0, v1, u0, u1)} of the fruits whose halo ball meets the image."""
        ids = [f for f, m in self.items() if m.centre is not None]
        if not ids:
            return {}
        boxes = sphere_boxes(hw, k, c2w, np.stack([self[f].centre for f in ids]),
                             np.array([self[f].radius * cfg.halo_factor + cfg.margin_m for f in ids]))
        full = (0, hw[0], 0, hw[1])
        return {f: full if b is None else b for f, b in zip(ids, boxes) if b is None or (b[0] < b[1] and b[2] < b[3])}

    def query(self, ids: list[int], points: np.ndarray, eye: np.ndarray, margin_m: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Points [P, 3] seen from `eye` against fruits `ids`: Evidence's rel, beyond, gap [P, F] and radius [F]."""
        centres = np.array([self[f].centre if self[f].centre is not None else [np.nan] * 3 for f in ids]).reshape(-1, 3)
        radii = np.array([self[f].radius for f in ids], np.float64)
        sq = (points ** 2).sum(1)[:, None] - 2 * dot3(points, centres) + (centres ** 2).sum(1)[None]
        rel = np.sqrt(np.maximum(sq, 0.0)) / radii
        ray = points - eye
        dist = np.linalg.norm(ray, axis=1, keepdims=True)
        beyond = dist - dot3(ray / dist, centres - eye)
        gap = np.full(rel.shape, np.inf)
        for j, f in enumerate(ids):
            near = np.flatnonzero(rel[:, j] <= 1.0 + 2 * margin_m / radii[j])
            if self[f].surface is not None and len(near):
                gap[near, j] = self[f].surface.query(points[near], distance_upper_bound=margin_m)[0]
        return rel, beyond, gap, radii


def fit_models(groups: list[list[int]], local: list[LocalFruit], views: dict, cfg: Config) -> FruitModels:
    """Each row fruit's model (`groups` of `local` fruits, `views` their slot views), fitted to its rendered points,
    moved by their median sensor offset where that exceeds the halo (a window can render a fruit cm off)."""
    out = FruitModels()
    for g in groups:
        svs = [views[(local[i].window_id, local[i].slot)][key] for i in g for key in local[i].frames]
        px = defaultdict(int)
        for i in g:
            px[local[i].class_id] += local[i].n_px
        m = FruitModel(max(px, key=px.get), np.concatenate([sv.points for sv in svs])).refit(cfg)
        offsets = [sv.sensor_offset for sv in svs if sv.sensor_offset is not None]
        if offsets and m.centre is not None:
            off = np.median(np.stack(offsets), 0)
            if np.linalg.norm(off) > (cfg.halo_factor - 1) * m.radius + cfg.margin_m:
                m.points, m.centre = m.points + off, m.centre + off
                m.refit(cfg)
        out[local[g[0]].fruit_id] = m
    return out


def detector_clusters(views: list[SegmentView], typical_radius: float, cfg: Config
                      ) -> tuple[np.ndarray, list[np.ndarray]]:
    """The fruits one row fruit holds by its detector segments `views`: clusters of centres closer than
    detector_split_m are two fruits where seen together in MIN_SPLIT_FRAMES frames, or in one with centres over
    TWO_FRUITS_APART x `typical_radius` apart. Returns (each view's cluster, -1 none; the clusters' centres, most
    pixels first), or (all -1, []) for one fruit."""
    labels = np.full(len(views), -1)
    if cfg.detector_split_m <= 0 or len(views) < 2:
        return labels, []
    pts = np.stack([v.centre for v in views])
    raw = fcluster(linkage(pts, "single"), cfg.detector_split_m, criterion="distance")
    frames_of, px = defaultdict(set), defaultdict(int)
    for v, c in zip(views, raw):
        frames_of[c].add(v.frame)
        px[c] += v.n_px
    centre = {c: np.median(pts[raw == c], 0) for c in frames_of}
    together = set()
    for a, b in combinations(sorted(frames_of), 2):
        shared = len(frames_of[a] & frames_of[b])
        apart = float(np.linalg.norm(centre[a] - centre[b]))
        if shared >= MIN_SPLIT_FRAMES or (shared and apart > TWO_FRUITS_APART * typical_radius):
            together |= {a, b}
    if not together:
        return labels, []
    order = sorted(together, key=lambda c: -px[c])
    rank = {c: i for i, c in enumerate(order)}
    return np.array([rank.get(c, -1) for c in raw]), [centre[c] for c in order]


def update(models: FruitModels, given: dict[int, list[np.ndarray]], seg_views: dict[int, list[SegmentView]],
           cfg: Config) -> tuple[FruitModels, dict[tuple[int, int], int]]:
    """New models after a round, the inputs unchanged. Each fruit is refitted to the points the round gave it
    (`given`), not to the slots the association saw (a slot can paint two touching fruits). A fruit whose detector
    segments (`seg_views`) form several clusters is split: cluster 0 keeps its id, each other joins the fruit
    within max_match_distance_m (or its sphere), else is new; a cluster seen only as a cap gets a sphere of the
    typical radius of the models passed in behind it. Returns the models and the next round's detector evidence:
    {(frame, segment): fruit id} of the split fruits' segments."""
    out, typical_radius = FruitModels(), models.typical_radius
    for f, m in models.items():
        if given.get(f):
            out[f] = FruitModel(m.class_id, np.concatenate(given[f]), m.centre, m.radius).refit(cfg)
        else:
            out[f] = replace(m)   # a copy: a cluster split off below may add points to it
    owners = {}
    for fruit, views in sorted(seg_views.items()):
        m = out[fruit]
        labels, centres = detector_clusters(views, typical_radius, cfg)
        if not centres:
            continue
        ids = [fruit]
        for c in centres[1:]:
            dist = {g: float(np.linalg.norm(o.centre - c)) for g, o in out.items()
                    if g not in ids and o.centre is not None}
            near = [(d, g) for g, d in dist.items() if d <= max(cfg.max_match_distance_m, out[g].radius + cfg.margin_m)]
            ids.append(min(near)[1] if near else max(out) + 1)
            if not near:
                out[ids[-1]] = FruitModel(m.class_id, np.zeros((0, 3)))
        for j, g in enumerate(ids):   # the clusters' models are fitted to their segments' points
            mine = [v for v, lab in zip(views, labels) if lab == j]
            pts = np.concatenate([v.points for v in mine])
            if j == 0 or out[g].centre is None:
                eye = np.mean([v.eye for v in mine], 0)
                out[g] = FruitModel(m.class_id, pts).refit(cfg, behind=(eye, typical_radius))
            else:
                out[g].points = np.concatenate([out[g].points, pts])
        owners.update({(v.frame, v.segment): ids[lab] for v, lab in zip(views, labels) if lab >= 0})
    return out, owners
