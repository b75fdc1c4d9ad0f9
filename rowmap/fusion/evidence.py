"""Per-frame evidence: for each pixel and candidate fruit, what the render, the detector and the fruit models say."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nerf.config import BASE_PIXELS
from nerf.surfaces import unproject
from rowmap.fusion.models import FruitModels
from rowmap.fusion.settings import Config

BORDER_BAND_PX = 8
"""pixels at 320x180 (scaled with the image): the edge band where the render is weakest (a fruit entering the
view is painted as leaf or as its neighbour)."""
BORDER_CONFIDENCE = 0.4
"""[0, 1]: the render's confidence in the border band (1 elsewhere)."""


@dataclass
class Frame:
    """The inputs of one fused frame."""

    frame_id: int
    label: np.ndarray    # [H, W] the render's fruit id; 0 = stuff, -1 = void (a dropped slot)
    depth: np.ndarray    # [H, W] m: the z-depth that places pixels (sensor where valid, else the render's)
    segments: np.ndarray | None   # [H, W] detector segment ids (0 = none); None: no detector output
    k: np.ndarray        # (fx, fy, cx, cy)
    c2w: np.ndarray      # [4, 4] camera pose in the row frame
    fruit: np.ndarray | None = None   # [H, W] the render's fruit probability; None: not rendered (taken as 0)


@dataclass
class Evidence:
    """What decides the pixels of one frame: P pixels (those a fruit could take), F candidate fruits (column 0 of
    every [P, F + 1] option array is background). The model distances are filled in by `part`."""

    pixels: np.ndarray      # [P] flat indices into the frame
    ids: np.ndarray         # [F] candidate fruit ids
    points: np.ndarray      # [P, 3] world points
    render: np.ndarray      # [P] option the render paints (0 = background or void)
    confidence: np.ndarray  # [P] the render's confidence, [0, 1]
    fruit: np.ndarray       # [P] the render's fruit probability, [0, 1] (a sliver its labels drop keeps it)
    detector: np.ndarray    # [P] option of the detector segment's fruit: -1 no segment, 0 a segment on no fruit
    segment: np.ndarray     # [P] detector segment id (0 = none)
    rel: np.ndarray | None = None      # [P, F] distance to the fruit's sphere centre / its radius (nan: no sphere)
    beyond: np.ndarray | None = None   # [P, F] m beyond the sphere's centre along the pixel's ray (nan: no sphere)
    gap: np.ndarray | None = None      # [P, F] m to the fruit's seen surface (inf: farther than margin_m)
    radius: np.ndarray | None = None   # [F] m (nan: no sphere)
    boxes: dict | None = None          # {fruit id: image box (v0, v1, u0, u1) of its halo ball}

    def part(self, rows: np.ndarray, cols: np.ndarray, models: FruitModels, eye: np.ndarray, cfg: Config
             ) -> "Evidence":
        """Pixels `rows` against candidates `cols` (ascending) with the models' distances; other options -> 0."""
        ids, points = self.ids[cols], self.points[rows]
        option = np.zeros(len(self.ids) + 1, np.int64)    # option here of each option of the whole frame
        option[np.asarray(cols, np.int64) + 1] = np.arange(1, len(cols) + 1)
        rel, beyond, gap, radii = models.query(ids.tolist(), points, eye, cfg.margin_m)
        det = self.detector[rows]
        return Evidence(self.pixels[rows], ids, points, option[self.render[rows]], self.confidence[rows],
                        self.fruit[rows], np.where(det > 0, option[np.maximum(det, 0)], det), self.segment[rows], rel,
                        beyond, gap, radii, self.boxes)


def frame_evidence(frame: Frame, models: FruitModels, owners: dict[tuple[int, int], int], cfg: Config) -> Evidence:
    """The evidence of one frame, every pixel against every candidate."""
    ev = pixel_evidence(frame, models, owners, cfg)
    return ev.part(np.arange(len(ev.pixels)), np.arange(len(ev.ids)), models, frame.c2w[:3, 3], cfg)


def pixel_evidence(frame: Frame, models: FruitModels, owners: dict[tuple[int, int], int], cfg: Config) -> Evidence:
    """One frame's evidence but the models' distances, for the fruits the render paints and those whose halo is in
    view. A segment's fruit: `owners`' ((frame, segment) -> fruit, after a split), else the one painted on most of
    it; none where that is background (the segment says some fruit is there; the fruit models say which)."""
    h, w = frame.label.shape
    boxes = models.in_view((h, w), frame.k, frame.c2w, cfg)
    ids = np.array(sorted(set(np.unique(frame.label[frame.label > 0]).tolist()) | set(boxes)), np.int64)
    seg = frame.segments if frame.segments is not None else np.zeros((h, w), np.int64)
    # a pixel only background can take: no render fruit, no segment, outside every fruit's halo ball
    keep = ((frame.label != 0) | (seg > 0)) & (frame.depth > 0)
    for f, (v0, v1, u0, u1) in boxes.items():
        bv, bu = np.nonzero((frame.depth[v0:v1, u0:u1] > 0) & ~keep[v0:v1, u0:u1])
        p = unproject(frame.depth, frame.k, frame.c2w, bv + v0, bu + u0)
        near = np.linalg.norm(p - models[f].centre, axis=1) <= models[f].radius * cfg.halo_factor + cfg.margin_m
        keep[bv[near] + v0, bu[near] + u0] = True
    v, u = np.nonzero(keep)
    on, n_lab = (frame.label >= 0) & (seg > 0), int(frame.label.max()) + 1
    owner = np.zeros(int(seg.max()) + 1, np.int64)   # segment -> what is painted on most of it (0: background)
    keys, n = np.unique(seg[on] * n_lab + frame.label[on], return_counts=True)
    order = np.argsort(n, kind="stable")   # the largest pair of each segment written last
    owner[keys[order] // n_lab] = keys[order] % n_lab
    for (f, s), g in owners.items():
        if f == frame.frame_id and s < len(owner):
            owner[s] = g
    column = np.zeros(max(int(ids.max(initial=0)), int(owner.max())) + 1, np.int64)
    column[ids] = np.arange(1, len(ids) + 1)   # fruit id -> its option (0: not a candidate)
    segment = seg[v, u]
    band = int(np.ceil(BORDER_BAND_PX * np.sqrt(max(1.0, h * w / BASE_PIXELS))))
    border = (v < band) | (v >= h - band) | (u < band) | (u >= w - band)
    return Evidence(pixels=v * w + u, ids=ids, points=unproject(frame.depth, frame.k, frame.c2w, v, u),
                    render=column[np.maximum(frame.label[v, u], 0)],
                    confidence=np.where(border, BORDER_CONFIDENCE, 1.0),
                    fruit=np.zeros(len(v)) if frame.fruit is None else frame.fruit[v, u].astype(np.float64),
                    detector=np.where(segment > 0, column[owner[segment]], -1), segment=segment, boxes=boxes)
