"""Fuse the windows' instance slots into row-level fruit ids and write per-frame panoptic PNGs with them."""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

import numpy as np
import pandas as pd
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

import schemas
from nerf.config import BASE_PIXELS
from nerf.geometry import pose_matrix, pose_txyzq
from nerf.panoptic.complete import sphere_boxes
from nerf.surfaces import fruit_sphere, robust_centre, unproject
from pipeline.classes import THING_IDS, VOID
from pipeline.images import ImageError, read_label, write_png
from pipeline.stage import StageContext
from rowmap.detections import dropped_segments, fruit_segments
from rowmap.geometry import (POSE_COLS, pixel_groups, runs_by_key, sphere_behind, subsample, window_alignments,
                             with_sensor_depth)
from rowmap.renders import PANOPTIC_KINDS, Renders, encode, read_depth
from rowmap.scoring import image_pixels_for

INPUTS = ("frames", "windows", "window_poses", "window_metrics", "nerf", "renders", "images", "detections_filtered")
MAX_GROUPS = 256
"""groups a slot's pixels can split into in one frame (further groups stay with the largest)."""
OUTPUTS = ("panoptic_frames", "panoptic", "fruit_slots")


@dataclass(frozen=True)
class Config:
    max_match_distance_m: float = 0.04
    """metres, > 0. Two windows' slots are the same fruit only if their 3D centres are closer than this. About
    half a fruit's diameter: neighbouring fruits' centres lie farther apart, two windows' estimates of one
    fruit closer. Scale it with the crop's fruit size; raise it when the windows' poses disagree by more
    than a few centimetres (window_alignment_max_m in the stage summary grows with such drift). Two slots of
    one window join one fruit only where they never share a frame and their centres lie this close: the
    window lost the fruit (painted it as leaf for a few frames) and painted it again with another slot."""
    strong_mask_overlap: float = 0.8
    """share in [0, 1]. Two slots are the same fruit up to strong_match_distance_m apart when, on the frames
    both windows rendered, this share of the smaller mask lies inside the other (pooled over those frames;
    their IoU must still reach min_mask_iou). A window that sees a fruit only as a sliver while it enters or
    leaves the image gets a poor centre from it and renders the fruit smaller than its neighbour does, so
    containment, not IoU, is the evidence there. Lower it to merge more such pairs (at the risk of merging
    touching fruits); 1 = only exact containment."""
    strong_match_distance_m: float = 0.08
    """metres, >= 0: the distance gate for slots whose masks overlap by strong_mask_overlap (0 or at most
    max_match_distance_m = no relaxed gate). About one fruit diameter."""
    min_mask_iou: float = 0.3
    """IoU in [0, 1]: on frames both windows rendered, the two slots' masks must overlap at least this much
    (pooled over those frames); slots neither window shows there are matched on distance alone. A fruit
    joined from three or more windows must meet it between every two of them (each window's slots of the
    fruit pooled): a stray piece a third window matched, with no frame in common, does not join a fruit whose
    mask it misses where the two windows both rendered. Raise it when touching fruits get merged, lower it
    when one fruit keeps two ids across windows."""
    group_gap_m: float = 0.03
    """metres, >= 0. In each rendered frame, a slot's pixels are un-projected (rendered depth) and split into
    groups: neighbouring pixels stay together when their 3D points lie closer than this gap, so a depth jump
    or pixels that do not touch in the image separate groups. The NeRF sometimes paints one slot over two
    fruits in a frame (a fruit and one behind or beside it). Each group is then placed on its own
    (split_distance_m below): a group on another fruit's surface joins the part of the slot that sees that
    fruit in other frames, or becomes a part of its own. 0 = a slot's pixels in a frame stay one group.
    Keep it above the depth step between neighbouring pixels on one steep surface (about 1 cm at 1 m) and
    below the depth gaps that separate a fruit from one behind it."""
    min_group_px: int = 50
    """pixels of the frame, >= 1: a group smaller than this stays with the slot's largest group in that frame
    (stray boundary pixels whose rendered depth falls on what lies behind them). Scale it with the image
    area."""
    split_distance_m: float = 0.08
    """metres, >= 0. A slot whose per-frame pixel groups (group_gap_m) have centres in clusters farther apart
    than this inside one window is split into several fruits (the NeRF gave one slot to two fruits); 0 =
    never split. About one fruit diameter; lower it for small fruits."""
    min_split_frames: int = 2
    """frames, >= 1. A split-off cluster becomes a fruit of its own only if it holds at least this many
    per-frame groups; a single frame's stray centre (a sliver at the image border, un-projected onto what
    lies behind it) rejoins the slot's main cluster. 1 = every cluster is a fruit."""
    centre: Literal["sphere", "median"] = "sphere"
    """a slot's 3D centre for the association: 'sphere' = centre of a sphere fitted to its seen surface;
    where that fit is not plausible (a shallow or partial cap fits a sphere far wider than the fruit), the
    centre of a sphere with the median radius of the row's plausible fits, placed behind the seen part as its
    cameras saw it (the median where that fails too); 'median' = median of the seen surface points (biased
    towards the cameras that saw it, so windows that saw a fruit from opposite sides disagree by
    centimetres). Use 'median' for crops whose fruits are far from round."""
    max_fruit_radius_m: float = 0.07
    """metres, > 0: a sphere fit with a larger radius is not a fruit (a flat patch, or pieces of several fruits
    one slot painted) and the median is used; such a fruit gets no sphere for track_margin_m either, so it
    takes no pixel from its neighbours and gives them those of its pixels that lie on their spheres. A sphere
    fitted to the seen surface of an elongated fruit (a pepper longer than wide, seen from one side) is wider
    than the fruit: its radius runs up to about 1.6 times the fruit's half-width. Set it about 1.5 times the
    largest fruit radius of the crop (sweet pepper about 0.03-0.045 m). Too large lets a fit to pieces of two
    touching fruits pass as one fruit's sphere (its pixels then go to it)."""
    align_windows: bool = True
    """bring every window into one row frame before fusing: each window refines its poses on its own, so two
    windows place one fruit where their own stretch of odometry put it, centimetres apart over a row with
    drift. The frames two windows share give the rigid transform between them; windows are chained from the
    first (whose frame, the odometry's near the row start, is the row frame). Off = each window's own frame
    (only for windows that share no frame, or to inspect the raw per-window poses)."""
    min_slot_px: int = 4
    """pixels, >= 1: slots with fewer pixels over all the window's frames are dropped (their pixels become
    void). Raise it when specks of a few pixels show up as fruits."""
    track_margin_m: float = 0.01
    """metres, >= 0. Each fused fruit gets a sphere fitted to its seen surface over all its windows and frames
    (where the fit is plausible: max_fruit_radius_m). In every fused frame a fruit pixel whose 3D point
    (placed with surface_depth) lies outside the sphere of the fruit it was given, by more than this
    margin, but inside another fruit's sphere (radius + margin) and at most this margin beyond that sphere's
    centre along the pixel's ray (on the half of the sphere that faces the camera: the half behind it is
    hidden by the fruit itself) goes to that fruit: a slot that painted a piece of a neighbour (a fruit
    entering or leaving the image, or one behind it) gives that piece back to the fruit whose surface it is,
    and a fruit seen past the outline of one in front of it is not given to the front fruit. A fruit without
    a plausible sphere (too few points, or pieces of several fruits) gives every pixel that lies on another
    fruit's sphere to that fruit. Pixels on no sphere keep their id. About the depth error of the spheres and
    the placed points; 0 = off."""
    surface_depth: Literal["sensor", "rendered"] = "sensor"
    """the depth that places a fused frame's fruit pixels for track_margin_m: 'sensor' = the recorded depth
    image where it has a valid pixel (the rendered depth elsewhere), 'rendered' = the NeRF's depth everywhere.
    The render is weakest where its window saw little: at the image border, where a fruit enters or leaves
    the view, and in the frames at a window's ends. There the rendered depth can put a fruit's pixels onto a
    neighbour's sphere, while the sensor measures the fruit's own surface. Use 'rendered' for a depth sensor
    whose error on fruits is larger than track_margin_m. The spheres are fitted to rendered points either way."""
    off_sphere_factor: float = 1.25
    """multiple of a fruit's sphere radius, 0 (off) or >= 1. In every fused frame, after track_margin_m, a pixel of a
    fruit with a sphere whose 3D point (placed with surface_depth) lies farther from the sphere's centre than this
    multiple of its radius plus track_margin_m is not that fruit: it becomes background (semantic class 0, no fruit
    id), unless a detector segment lying mostly on that fruit covers it (the detector, an independent witness on the
    fused frames, shows the fruit there) and the point does not lie behind the sphere (more than radius +
    track_margin_m beyond its centre along the pixel's ray: a detector mask reaching past the fruit's outline onto a
    fruit further back is no witness there; a segment lying mostly behind the sphere is another fruit under this id
    and keeps its pixels for detector_split_m where they are at least min_group_px). The render paints a fruit's
    silhouette wider than the fruit, over the leaves and background behind it (the sensor measures them there), and
    paints a fruit that enters or leaves the image in a recording's first or last frames with a neighbour's id; the
    spheres fitted to elongated fruits are wider than the fruits, so the pixels cleared lie well beyond the fruit. A
    fruit whose rendered surface lies off the sensor's by more than the rule tolerates beyond the sphere ((this
    multiple - 1) x radius + track_margin_m, in the median over the fruit's views) keeps its pixels: its sphere,
    fitted to the render, is no witness of where the fruit is (the render can misplace a fruit that a window saw in
    few frames by several centimetres); border_band_px then looks for its seen surface where the sensor puts it.
    Lower it (towards 1) to clear more of the halo, raise it where fruits are far from round or the spheres are poor
    (a fruit's own pixels beyond its sphere are lost). Needs spheres (track_margin_m > 0); with surface_depth
    'rendered' the halo lies on the render's fruit surface and is not cleared."""
    detector_fill: bool = True
    """in every fused frame, give a fruit the pixels of its detector segment that the render left as stuff or
    void and whose 3D point (placed with surface_depth) lies within the fruit's sphere (radius +
    track_margin_m), not farther than track_margin_m beyond the sphere's centre along the pixel's ray (a leaf
    a little behind the fruit's outline lies near the sphere but behind it), and deeper in it than in any other
    fruit's sphere. A fruit's segment is the detector segment holding most of the fruit's pixels in that
    frame, and more of them than of any other fruit's. The NeRF often paints a fruit's silhouette, or the
    sliver of a fruit entering or leaving the image, as leaf; the detector and the depth sensor still see the
    fruit there. Needs spheres (track_margin_m > 0) and detector output; segments the depth filter dropped are
    not used. Off = the fused fruits have the render's pixels only."""
    border_band_px: int = 8
    """reference pixels (as in a 320x180 image, scaled with the image's size), >= 0; 0 = off. In a band this
    wide along the image's edges, a pixel whose 3D point (placed with surface_depth) lies within track_margin_m
    of a fruit's seen surface goes to that fruit, unless the fruit it carries has its surface there too (the
    nearest surface wins). A fruit's seen surface: the points its windows rendered of it over all frames that
    lie inside its sphere (the sphere drops what a slot painted beyond the fruit; fruits without a plausible
    sphere have none). A fruit entering or leaving the view (or cut off by the image's edge) shows a sliver at
    the edge; the detector misses or drops most cut-off fruits, so the render learns to paint that sliver as
    leaf or with the neighbour's slot, while the frames that see the fruit whole still place its surface. The
    seen surface, not the sphere's front, because a sphere fitted to an elongated fruit is wider than the
    fruit and passes centimetres in front of its sides, where the sliver is. A leaf beside the fruit, in front
    of it or behind it is not taken, so a wider band mostly costs time. A fruit whose render lies off the
    sensor's surface (see off_sphere_factor) has its seen surface moved by the median offset from its rendered
    to its measured points. Needs spheres (track_margin_m > 0)."""
    regrow_min_px: int = 12
    """reference pixels (as in a 320x180 image, scaled with the image's area), >= 0; 0 = off. In every fused
    frame between the first and the last frame a fruit's slots paint it in, and in every fused frame where it
    holds pixels after the rules before this one (track_margin_m, detector_fill, border_band_px), a fruit whose
    render shows fewer of its pixels than there are stuff pixels whose 3D point (placed with surface_depth) lies
    within track_margin_m of its seen surface (see border_band_px) and not beyond its sphere's centre takes
    those pixels, where they number at least this many: the render hid most of what the depth sensor measures
    of the fruit there (a glimpse between leaves or past a neighbour, painted as leaf). A fruit the render
    shows well keeps its outline as painted, so the leaf along it is not taken. About the smallest view of a
    fruit that can carry an id (nerf_fit.panoptic.min_segment_px); needs track_margin_m > 0."""
    regrow_passes: int = 2
    """passes of regrow_min_px, >= 1. The first runs as each fused frame is written, on the seen surface the
    windows' renders give a fruit. Each further pass, once every fused frame is written (and split by
    detector_split_m), adds to the seen surface of each fruit with a sphere (whose render lies on the sensor's
    surface: off_sphere_factor) the points of the pixels it holds in the fused frames, placed with
    surface_depth (max_points_per_view per frame), and runs regrow_hidden again on every frame for the fruits
    in view there: from the frame before the first fused frame that shows the fruit to the frame after the
    last. A side of a fruit its windows painted as leaf or as a neighbour, and that the rules gave back in some
    frames, then counts as its surface in the frames where it is hidden again; a fruit entering or leaving the
    view, or lost behind a leaf for a frame, comes back in those frames. A fused fruit whose render points fit
    no plausible sphere (a cap seen from one side) takes part with the sphere its grown points fit, where they
    fit one. Each pass reads the fused frames twice; 1 = the first pass only."""
    detector_split_m: float = 0.03
    """metres, >= 0; 0 = off. A fused fruit that the detector shows as several fruits is split. In every fused
    frame each detector segment lying mostly on fused fruits is given to the fruit holding most of it (at least
    min_group_px of its pixels) and yields a centre there: the median of those pixels' points, placed with
    surface_depth. Over the row a fruit's segment centres are linked into clusters where closer than this
    distance (single linkage). Where two clusters, each seen in at least min_split_frames frames, are seen
    together (two segments in one frame) in at least min_split_frames frames, the fused fruit holds two
    fruits: the NeRF painted two touching fruits with one slot for their whole visible stretch, most often at
    the row's ends where one window alone sees them. Two clusters seen together in fewer frames (one frame
    will do) are two fruits too where the smaller one's centre lies outside the fused fruit's sphere (radius +
    track_margin_m), or the fused fruit has no plausible sphere; and a cluster whose centre lies outside the
    sphere is a fruit beside the largest cluster even where the two never share a frame: a fruit the
    recording's first or last frames show once or twice, painted with its neighbour's id (the detector may
    miss the neighbour in those frames). The cluster with the most pixels keeps the fruit's id;
    another joins an existing fruit at its place (centres within max_match_distance_m, or one inside the
    other's sphere) or becomes a new fruit (ids after those of the row). In each frame a cluster's segments
    go to it, the fruit's other pixels within track_margin_m of a cluster's seen surface (its segments'
    points) to the cluster whose surface lies nearest, and the rest to the cluster whose sphere they lie
    deepest in (track_margin_m and detector_fill then run again with those spheres) or, where a cluster has no
    plausible sphere, to the nearest surface's cluster where the detector shows it in the frame (else to the
    cluster with the most pixels). About the largest shift of a fruit's seen-surface centre between two
    neighbouring frames (it moves as the fruit enters the view or hides behind a leaf), well under the distance
    of two touching fruits' centres. Needs detector output."""
    compose_shared_frames: bool = True
    """in a frame several overlapping windows rendered, take each fruit's pixels from the window that saw the
    fruit in the most rendered frames (then pixels), not every pixel from the window whose centre is nearest.
    A window renders a fruit it saw only while the fruit entered or left its stretch of row smaller than it is,
    or paints it with a neighbour's id; the neighbouring window saw it whole. Off = the nearest window only."""
    max_points_per_view: int = 400
    """points, >= 1: 3D points kept per slot and frame for the centre, and pixels used per slot and frame for
    the offset between rendered and measured points (evenly subsampled). More points cost time and change the
    centres little; lower it on large images to save time."""

    def __post_init__(self) -> None:
        if not self.max_match_distance_m > 0:
            raise ValueError(f"panoptic_fusion.max_match_distance_m must be > 0, got {self.max_match_distance_m}")
        if not 0.0 <= self.min_mask_iou <= 1.0:
            raise ValueError(f"panoptic_fusion.min_mask_iou must be in [0, 1], got {self.min_mask_iou}")
        if not 0.0 <= self.strong_mask_overlap <= 1.0 or not self.strong_match_distance_m >= 0.0:
            raise ValueError("panoptic_fusion.strong_mask_overlap must be in [0, 1] and strong_match_distance_m >= 0, "
                             f"got {self.strong_mask_overlap}, {self.strong_match_distance_m}")
        if not self.max_fruit_radius_m > 0:
            raise ValueError(f"panoptic_fusion.max_fruit_radius_m must be > 0, got {self.max_fruit_radius_m}")
        if self.split_distance_m < 0 or self.min_slot_px < 1 or self.max_points_per_view < 1 or self.min_split_frames < 1:
            raise ValueError("panoptic_fusion: split_distance_m must be >= 0, min_slot_px, max_points_per_view and "
                             "min_split_frames >= 1")
        if not self.track_margin_m >= 0:
            raise ValueError(f"panoptic_fusion.track_margin_m must be >= 0, got {self.track_margin_m}")
        if not (self.off_sphere_factor == 0 or self.off_sphere_factor >= 1):
            raise ValueError(f"panoptic_fusion.off_sphere_factor must be 0 (off) or >= 1, got {self.off_sphere_factor}")
        if self.border_band_px < 0:
            raise ValueError(f"panoptic_fusion.border_band_px must be >= 0, got {self.border_band_px}")
        if self.regrow_min_px < 0 or self.regrow_passes < 1:
            raise ValueError("panoptic_fusion: regrow_min_px must be >= 0 and regrow_passes >= 1, got "
                             f"{self.regrow_min_px}, {self.regrow_passes}")
        if not self.detector_split_m >= 0:
            raise ValueError(f"panoptic_fusion.detector_split_m must be >= 0, got {self.detector_split_m}")
        if self.group_gap_m < 0 or self.min_group_px < 1:
            raise ValueError(f"panoptic_fusion: group_gap_m must be >= 0 and min_group_px >= 1, got "
                             f"{self.group_gap_m}, {self.min_group_px}")


def window_views(windows: pd.DataFrame, window_poses: pd.DataFrame, window_metrics: pd.DataFrame,
                 renders: Renders, ctx: StageContext) -> pd.DataFrame:
    """(window_id, frame_id, offset, pose) of every rendered validation frame of the fitted windows.
    Failed windows and windows without panoptic renders are skipped with a counted note; a window with
    panoptic renders for some validation frames but not others is an error naming what is missing."""
    ok = set(window_metrics.loc[window_metrics.status == "ok", "window_id"].astype(int))
    for wid in sorted(set(window_metrics.window_id.astype(int)) - ok):
        ctx.count("windows_failed_skipped")
        ctx.note(f"window {wid} failed in nerf_fit; its frames are not fused")
    val = windows[windows.split == "val"][["window_id", "frame_id", "offset"]]
    v = val.merge(window_poses, on=["window_id", "frame_id"], how="inner", suffixes=("", "_pose"))
    rows = []
    for wid, g in v.groupby("window_id"):
        if int(wid) not in ok:
            continue
        have = [renders.has(int(wid), int(f), *PANOPTIC_KINDS) for f in g.frame_id]
        if not any(have):
            ctx.count("windows_without_panoptic_renders")
            ctx.note(f"window {wid}: no panoptic renders ({'/'.join(PANOPTIC_KINDS)}) in renders.parquet; skipped")
            continue
        if not all(have):
            f = int(g.frame_id.to_numpy()[~np.asarray(have)][0])
            missing = [k for k in PANOPTIC_KINDS if not renders.has(int(wid), f, k)]
            raise ImageError(f"window {wid}, validation frame {f}: renders.parquet lists no {'/'.join(missing)} "
                             f"render while other validation frames of the window have theirs; rerun "
                             f"`pag nerf_fit --force`")
        rows.append(g)
    if not rows:
        return pd.DataFrame(columns=["window_id", "frame_id", "offset", "c2w"])
    out = pd.concat(rows, ignore_index=True)
    out["c2w"] = list(pose_matrix(out[list(POSE_COLS)].to_numpy(np.float64)))
    return out[["window_id", "frame_id", "offset", "c2w"]]


def read_render(renders: Renders, wid: int, fid: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(semantic, instance, depth in m) of one rendered frame, checked against the frame's image size."""
    return tuple(renders.read(wid, fid, k, shape) for k in PANOPTIC_KINDS)  # type: ignore[return-value]


# -- fusion ----------------------------------------------------------------------------------------------

def code(slot, group):
    """One number for a slot's pixel group in a frame: the keys of the lookup from groups to fruits and the
    pixels of the masks of frames several windows rendered. Integers or integer arrays (int32 or wider)."""
    return slot * MAX_GROUPS + group


@dataclass
class SlotView:
    """One pixel group of one slot of one window in one rendered frame."""

    n_px: int
    class_px: np.ndarray       # [N_CLASSES + 1] pixel counts per thing/stuff class
    points: np.ndarray         # [n, 3] world points (subsampled)
    depth_gap: float = np.nan  # median rendered - sensor z-depth (m) over its pixels with both; nan: none
    sensor_offset: np.ndarray | None = None
    """[3] median of (point placed with the sensor depth - point placed with the rendered one) over the same
    pixels (at most max_points_per_view of them); None without a sensor depth"""
    eye: np.ndarray | None = None
    """[3] the camera centre of the frame (row frame)"""


@dataclass
class LocalFruit:
    """A window-local fruit: (window, slot, part)."""

    window_id: int
    slot: int
    part: int
    frames: list[tuple[int, int]]
    """(frame_id, group) of the slot's per-frame pixel groups that make this part."""
    n_px: int
    class_id: int
    centre: np.ndarray | None
    fruit_id: int = 0
    drop_reason: str = ""
    median: np.ndarray | None = None
    """median of the seen surface points (the fallback position estimate; `centre` may be a sphere fit's)."""
    members: list[int] = field(default_factory=list)


def split_frames(frame_centres: dict, dist_m: float, min_frames: int = 1) -> list[list]:
    """Single-linkage clusters of a slot's per-frame centres, keyed by frame or by (frame, group) (keys
    without a centre join the largest cluster, and so do clusters of fewer than `min_frames` keys)."""
    fids = [f for f, c in frame_centres.items() if c is not None]
    rest = [f for f, c in frame_centres.items() if c is None]
    if dist_m <= 0 or len(fids) < 2:
        return [sorted(fids + rest)]
    pts = np.stack([frame_centres[f] for f in fids])
    parent = list(range(len(fids)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    for i, j in zip(*np.nonzero(np.triu(d <= dist_m, 1))):
        parent[find(i)] = find(j)
    groups: dict[int, list[int]] = defaultdict(list)
    for i, f in enumerate(fids):
        groups[find(i)].append(f)
    out = sorted((sorted(g) for g in groups.values()), key=lambda g: (-len(g), g[0]))
    small = [f for g in out[1:] if len(g) < min_frames for f in g]
    out = [sorted(out[0] + rest + small)] + [g for g in out[1:] if len(g) >= min_frames]
    return out


def centre_distance(a: LocalFruit, b: LocalFruit) -> float:
    """Distance of two local fruits: the smaller of their centres' and their medians' distances. The sphere
    centre does not move with the view, but on a fruit seen as a few noisy pixels (the far row) two fits can
    disagree where the medians agree."""
    d = float(np.linalg.norm(a.centre - b.centre))
    if a.median is not None and b.median is not None:
        d = min(d, float(np.linalg.norm(a.median - b.median)))
    return d


class MaskOverlaps:
    """The slot masks of the frames several windows rendered (`masks`: {(window, frame): [H, W] slot codes,
    0 = no slot}) read as joint histograms: per pair of windows and frame, the pixels of each pair of codes
    (one per window), counted once and kept. Every mask overlap of the association (pair_cost, associate's
    group and piece checks) is a sum over a few dozen histogram entries, not over the masks' pixels."""

    def __init__(self, masks: dict[tuple[int, int], np.ndarray]):
        self.masks = masks
        by_frame: dict[int, list[int]] = defaultdict(list)
        for w, f in masks:
            by_frame[f].append(w)
        self.shared: dict[tuple[int, int], list[int]] = defaultdict(list)
        """(window, window), the smaller first -> the frames both rendered"""
        for f, ws in sorted(by_frame.items()):
            ws = sorted(ws)
            for i, wa in enumerate(ws):
                for wb in ws[i + 1:]:
                    self.shared[(wa, wb)].append(f)
        self._joint: dict[tuple[int, int, int], list[tuple[int, int, int]]] = {}

    def frames(self, wa: int, wb: int) -> list[int]:
        """The frames windows wa and wb both rendered."""
        return self.shared.get((min(wa, wb), max(wa, wb)), [])

    def joint(self, wa: int, wb: int, f: int) -> list[tuple[int, int, int]]:
        """(code in window wa, code in window wb, pixels) over frame f's pixels where either mask has a slot
        (0 = no slot there)."""
        lo, hi = min(wa, wb), max(wa, wb)
        if (lo, hi, f) not in self._joint:
            a, b = self.masks[(lo, f)].ravel(), self.masks[(hi, f)].ravel()
            on = (a != 0) | (b != 0)
            packed = (a[on].astype(np.int64) << 32) | (b[on].astype(np.int64) & 0xFFFFFFFF)
            keys, n = np.unique(packed, return_counts=True)
            self._joint[(lo, hi, f)] = list(zip((keys >> 32).tolist(), (keys & 0xFFFFFFFF).tolist(), n.tolist()))
        out = self._joint[(lo, hi, f)]
        return out if wa == lo else [(y, x, n) for x, y, n in out]


def frame_codes(lf: LocalFruit) -> dict[int, set[int]]:
    """frame -> the slot codes (the masks' values) of a local fruit's pixel groups there."""
    out: dict[int, set[int]] = defaultdict(set)
    for f, g in lf.frames:
        out[f].add(int(code(lf.slot, g)))
    return out


def pair_cost(a: LocalFruit, b: LocalFruit, overlaps: MaskOverlaps, cfg: Config) -> float:
    """Matching cost of two local fruits of different windows (inf = not the same fruit):
    distance / gate + (1 - IoU) with IoU pooled over the frames both windows rendered (0.5 if neither
    shows the fruit on any such frame). Centres farther apart than cfg.max_match_distance_m still match, up
    to cfg.strong_match_distance_m, when the smaller masks lie inside the other by cfg.strong_mask_overlap."""
    if a.centre is None or b.centre is None:
        return np.inf
    dist = centre_distance(a, b)
    if dist > max(cfg.max_match_distance_m, cfg.strong_match_distance_m):
        return np.inf
    inter = union = smaller = 0
    codes_a, codes_b = frame_codes(a), frame_codes(b)
    for f in overlaps.frames(a.window_id, b.window_id):
        ca, cb = codes_a.get(f, set()), codes_b.get(f, set())
        n_a = n_b = 0
        for x, y, n in overlaps.joint(a.window_id, b.window_id, f):
            in_a, in_b = x in ca, y in cb
            n_a += n if in_a else 0
            n_b += n if in_b else 0
            union += n if (in_a or in_b) else 0
            inter += n if (in_a and in_b) else 0
        smaller += min(n_a, n_b)
    iou = inter / union if union else 0.5
    if union and iou < cfg.min_mask_iou:
        return np.inf
    if dist > cfg.max_match_distance_m and not (smaller and inter / smaller >= cfg.strong_mask_overlap):
        return np.inf
    return dist / cfg.max_match_distance_m + (1.0 - iou)


def associate(fruits: list[LocalFruit], masks: dict[tuple[int, int], np.ndarray], cfg: Config) -> list[list[int]]:
    """Groups of local-fruit indices that are one fruit. Per window pair a Hungarian assignment on
    `pair_cost`; accepted pairs are then merged cheapest first (union-find) unless the merge would put two
    local fruits of one window that share a frame, or lie farther apart than cfg.max_match_distance_m, into
    one fruit, or would join windows whose masks of the fruit overlap under cfg.min_mask_iou. A local fruit
    left alone then joins the fruit of the other windows whose masks hold most of its pixels (on the frames
    they share), where its centre lies within cfg.max_match_distance_m of that fruit's: a piece its window
    painted with a second slot beside the one that holds the fruit."""
    by_window: dict[int, list[int]] = defaultdict(list)
    for i, lf in enumerate(fruits):
        if lf.centre is not None:
            by_window[lf.window_id].append(i)
    wids = sorted(by_window)
    gate = max(cfg.max_match_distance_m, cfg.strong_match_distance_m)
    overlaps = MaskOverlaps(masks)
    # a box around each window's centres and medians: windows whose boxes lie farther apart than the gate
    # hold no pair within it (a row's windows meet only their neighbours; this keeps the pairs linear in length)
    box = {}
    for w, idx in by_window.items():
        pts = np.stack([p for i in idx for p in (fruits[i].centre, fruits[i].median) if p is not None])
        box[w] = (pts.min(0), pts.max(0))
    edges: list[tuple[float, int, int]] = []
    for a_i, wa in enumerate(wids):
        for wb in wids[a_i + 1:]:
            gap = np.maximum(0.0, np.maximum(box[wa][0] - box[wb][1], box[wb][0] - box[wa][1]))
            if np.linalg.norm(gap) > gate:
                continue
            ia, ib = by_window[wa], by_window[wb]
            near = np.array([[centre_distance(fruits[i], fruits[j]) <= gate for j in ib] for i in ia])
            if not near.any():
                continue
            cost = np.full(near.shape, np.inf)
            for r, c in zip(*np.nonzero(near)):
                cost[r, c] = pair_cost(fruits[ia[r]], fruits[ib[c]], overlaps, cfg)
            finite = np.isfinite(cost)
            if not finite.any():
                continue
            rows, cols = linear_sum_assignment(np.where(finite, cost, 1e6))  # large finite, never inf
            edges += [(float(cost[r, c]), ia[r], ib[c]) for r, c in zip(rows, cols) if finite[r, c]]
    parent = list(range(len(fruits)))
    members = [[i] for i in range(len(fruits))]
    codes_of = [frame_codes(lf) for lf in fruits]   # per local fruit: frame -> its slot codes there

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def compatible(ri: int, rj: int) -> bool:
        """Two groups may merge where every two of their local fruits from one window are slots of one fruit in
        turn (never in the same frame, and within cfg.max_match_distance_m of each other) and where, on every
        frame two of the merged group's windows both rendered, their masks overlap (group_iou)."""
        for i in members[ri]:
            for j in members[rj]:
                if fruits[i].window_id == fruits[j].window_id and (
                        codes_of[i].keys() & codes_of[j].keys()
                        or centre_distance(fruits[i], fruits[j]) > cfg.max_match_distance_m):
                    return False
        return group_iou(members[ri] + members[rj]) >= cfg.min_mask_iou

    def group_iou(idx: list[int]) -> float:
        """Smallest mask IoU, over the pairs of windows in fruits[idx], of the windows' masks of those fruits
        pooled over the frames both windows rendered (1 where no pair shares a frame)."""
        codes: dict[int, dict[int, set[int]]] = defaultdict(lambda: defaultdict(set))
        for i in idx:
            for f, cs in codes_of[i].items():
                codes[fruits[i].window_id][f] |= cs
        wins, worst = sorted(codes), 1.0
        for a_i, wa in enumerate(wins):
            for wb in wins[a_i + 1:]:
                inter = union = 0
                for f in overlaps.frames(wa, wb):
                    ca, cb = codes[wa].get(f, set()), codes[wb].get(f, set())
                    for x, y, n in overlaps.joint(wa, wb, f):
                        if x in ca or y in cb:
                            union += n
                            inter += n if (x in ca and y in cb) else 0
                if union:
                    worst = min(worst, inter / union)
        return worst

    for _, i, j in sorted(edges):
        ri, rj = find(i), find(j)
        if ri != rj and compatible(ri, rj):
            parent[rj] = ri
            members[ri] += members[rj]
    # a local fruit left alone whose mask lies mostly on one fruit of the other windows, within the gate of it,
    # is a second slot its window painted on that fruit (a piece beside the slot that holds the fruit)
    owner = {(lf.window_id, f, c): k for k, lf in enumerate(fruits) for f, cs in codes_of[k].items() for c in cs}
    for i, lf in enumerate(fruits):
        if lf.centre is None or find(i) != i or len(members[i]) > 1:
            continue
        mine = codes_of[i]
        on: dict[int, int] = defaultdict(int)   # group root -> pixels of this fruit's mask on its masks
        total = 0
        for (wa, wb), fids in overlaps.shared.items():
            if lf.window_id not in (wa, wb):
                continue
            other = wb if lf.window_id == wa else wa
            for f in fids:
                if f not in mine:
                    continue
                for own, theirs, n in overlaps.joint(lf.window_id, other, f):
                    if own in mine[f]:
                        total += n
                        k = owner.get((other, f, theirs))
                        if k is not None and fruits[k].centre is not None:
                            on[find(k)] += n
        if not on:
            continue
        root, n_on = max(on.items(), key=lambda kv: kv[1])
        if n_on >= total / 2 and min(centre_distance(lf, fruits[k]) for k in members[root]) <= cfg.max_match_distance_m:
            parent[i] = root
            members[root] += members[i]
    groups: dict[int, list[int]] = defaultdict(list)
    for i, lf in enumerate(fruits):
        if lf.centre is not None:
            groups[find(i)].append(i)
    return list(groups.values())


def fruit_points(groups: list[list[int]], local: list[LocalFruit], slot_views: dict) -> dict[int, np.ndarray]:
    """{fruit id: seen surface points [N, 3]} of the fused fruits (groups of local fruits carrying their fruit
    id): the points of all their windows' slot views."""
    out = {}
    for g in groups:
        pts = [slot_views[(local[i].window_id, local[i].slot)][fg].points for i in g for fg in local[i].frames]
        out[local[g[0]].fruit_id] = np.concatenate(pts) if pts else np.zeros((0, 3))
    return out


def fruit_render_gaps(groups: list[list[int]], local: list[LocalFruit], slot_views: dict
                      ) -> dict[int, tuple[float, np.ndarray]]:
    """{fruit id: (median over its slot views (`groups` of `local` fruits) of their depth_gap (rendered - sensor
    z-depth, m), median of their sensor_offset [3])} of the fused fruits with a sensor depth in some view."""
    out = {}
    for g in groups:
        views = [slot_views[(local[i].window_id, local[i].slot)][fg] for i in g for fg in local[i].frames]
        views = [sv for sv in views if sv.sensor_offset is not None]
        if views:
            out[local[g[0]].fruit_id] = (float(np.median([sv.depth_gap for sv in views])),
                                         np.median(np.stack([sv.sensor_offset for sv in views]), axis=0))
    return out


def render_off_sensor(spheres: dict[int, tuple[np.ndarray, float]], gaps: dict[int, tuple[float, np.ndarray]],
                      cfg: Config) -> dict[int, np.ndarray]:
    """{fruit id: its sensor offset [3]} of the fruits with a sphere whose rendered surface lies off the sensor's
    (`gaps`: fruit_render_gaps) by more than off_sphere_factor tolerates beyond the sphere ((factor - 1) x
    radius + track_margin_m). Their sphere, fitted to the render, does not say where the sensor sees the
    fruit: clear_off_sphere leaves their pixels be, and border_surfaces looks for their seen surface moved by
    the offset. Where a window saw a fruit from few frames (a recording's first or last frames) its render
    can place the fruit several centimetres off the measured surface."""
    if cfg.off_sphere_factor <= 0:
        return {}
    return {f: gaps[f][1] for f, (_, r) in spheres.items()
            if f in gaps and abs(gaps[f][0]) > (cfg.off_sphere_factor - 1) * r + cfg.track_margin_m}


def moved_surfaces(clouds: dict[int, cKDTree], offsets: dict[int, np.ndarray]) -> dict[int, cKDTree]:
    """`clouds` (seen surfaces) with those of the fruits in `offsets` moved by their offset."""
    return {f: cKDTree(np.asarray(c.data) + offsets[f]) if f in offsets else c for f, c in clouds.items()}


def fruit_spheres(points: dict[int, np.ndarray], max_radius_m: float) -> dict[int, tuple[np.ndarray, float]]:
    """{fruit id: (sphere centre [3], radius)} of the fruits whose seen surface `points` (fruit_points) fits a
    plausible sphere (nerf.surfaces.fruit_sphere)."""
    out = {}
    for fruit_id, pts in points.items():
        if len(pts) < 20:
            continue
        fit = fruit_sphere(pts, max_radius_m)
        if fit is not None:
            out[fruit_id] = (fit[0], float(fit[1]))
    return out


def surface_clouds(points: dict[int, np.ndarray], spheres: dict[int, tuple[np.ndarray, float]],
                   voxel_m: float) -> dict[int, cKDTree]:
    """{fruit id: k-d tree of its seen surface} for the fruits with a sphere: their points (fruit_points) that
    lie inside the sphere, one per voxel_m cube. The sphere drops what the windows' slots painted beyond the
    fruit (a leaf behind its outline, a piece of a neighbour); the points keep the fruit's own shape, which a
    sphere fitted to an elongated fruit does not (it is wider than the fruit, so its surface misses the fruit's
    sides)."""
    out = {}
    for f, (c, r) in spheres.items():
        pts = points.get(f, np.zeros((0, 3)))
        pts = pts[np.linalg.norm(pts - c, axis=1) <= r]
        if len(pts):
            if voxel_m > 0:
                pts = pts[np.unique(np.floor(pts / voxel_m).astype(np.int64), axis=0, return_index=True)[1]]
            out[f] = cKDTree(pts)
    return out


def seen_surfaces(points: dict[int, np.ndarray], spheres: dict[int, tuple[np.ndarray, float]],
                  cfg: Config) -> dict[int, cKDTree]:
    """surface_clouds for border_band_px and regrow_min_px ({} when both are off), one point per cube of half
    track_margin_m: the nearest kept point then lies within the margin of where a dropped one was."""
    return surface_clouds(points, spheres, cfg.track_margin_m / 2) if cfg.border_band_px or cfg.regrow_min_px else {}


def sphere_arrays(spheres: dict[int, tuple[np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fruit ids [S] sorted, centres [S, 3], radii [S]) of {fruit id: (centre, radius)}, for the surface rules."""
    ids = np.array(sorted(spheres))
    return ids, np.stack([spheres[int(i)][0] for i in ids]), np.array([spheres[int(i)][1] for i in ids])


def relabel_by_surface(inst: np.ndarray, depth: np.ndarray, k: np.ndarray, c2w: np.ndarray,
                       spheres: dict[int, tuple[np.ndarray, float]], margin_m: float) -> int:
    """Give each fruit pixel of a fused frame (`inst` [H, W] fruit ids, changed in place; z-depth in m that
    places the pixels (surface_depth), intrinsics k = (fx, fy, cx, cy), pose c2w) whose 3D point lies more than
    margin_m outside its own fruit's sphere but within another's (radius + margin_m) to that fruit (the one it
    lies deepest in: smallest distance / radius). A sphere takes only points on its half facing the camera (at
    most margin_m beyond its centre along the pixel's ray, beyond_centre): a point further back would be hidden
    by that fruit, so it is the surface of something behind it (a fruit seen past its outline). A fruit without
    a sphere (too few points, or no plausible fit: most often a sliver a window gave a slot of its own) counts
    as outside its own sphere everywhere, so its pixels that lie on another fruit's sphere join that fruit.
    Pixels on no sphere keep their id. Returns the pixels moved."""
    if margin_m <= 0 or not spheres:
        return 0
    ids, centres, radii = sphere_arrays(spheres)
    # only the spheres whose image box is in the frame can hold a pixel's point (sphere_boxes)
    boxes = sphere_boxes(inst.shape, k, c2w, centres, radii + margin_m)
    seen = np.array([b is None or (b[0] < b[1] and b[2] < b[3]) for b in boxes])
    if not seen.any():
        return 0
    column = np.full(max(int(inst.max()), int(ids.max())) + 1, -1)  # fruit id -> its sphere among those in view
    column[ids[seen]] = np.arange(int(seen.sum()))                    # (-1: none, or out of view)
    ids, centres, radii = ids[seen], centres[seen], radii[seen]
    v, u = np.nonzero((inst > 0) & (depth > 0))  # a fruit without a sphere has no own sphere to lie outside
    if not len(v):
        return 0
    own = column[inst[v, u]]
    p = unproject(depth, k, c2w, v, u)
    rel = np.linalg.norm(p[:, None] - centres[None], axis=2) / radii           # [P, S] distance / radius
    reach = 1.0 + margin_m / radii
    rows = np.arange(len(v))
    col = np.maximum(own, 0)
    off_own = (own < 0) | (rel[rows, col] > reach[col])    # no own sphere in view holds none of them
    past = beyond_centre(p[:, None], c2w[:3, 3], centres)                    # [P, S]
    score = np.where((rel <= reach[None]) & (past <= margin_m), rel, np.inf)
    best = score.argmin(1)
    move = off_own & np.isfinite(score[rows, best]) & (best != own)
    inst[v[move], u[move]] = ids[best[move]]
    return int(move.sum())


def beyond_centre(points: np.ndarray, eye: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """[N] how far each point [N, 3] lies along its ray from the camera centre `eye` [3] beyond the sphere
    centre (`centres` [3] or [N, 3]) seen on that ray (m; negative in front of it). A fruit's seen surface
    faces the camera: in front of its centre, or about level with it at the outline. Broadcasts over leading
    axes: points [N, 1, 3] and centres [S, 3] give [N, S]."""
    ray = points - eye
    dist = np.linalg.norm(ray, axis=-1)
    return dist - ((ray / dist[..., None]) * (centres - eye)).sum(axis=-1)


def fruit_segment_pairs(inst: np.ndarray, segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(fruit ids, segment ids) of the (fruit, detector segment) pairs sharing pixels (`inst` [H, W] fruit ids,
    `segments` [H, W] ids, 0 = none), the pair sharing the most pixels first (ties: smaller fruit id, then
    segment id)."""
    both = (inst > 0) & (segments > 0)
    if not both.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    base = int(segments.max()) + 1
    keys, n = np.unique(inst[both].astype(np.int64) * base + segments[both], return_counts=True)
    keys = keys[np.argsort(-n, kind="stable")]
    return keys // base, keys % base


def segment_owners(fruit: np.ndarray, seg: np.ndarray, n_segments: int) -> np.ndarray:
    """[n_segments] the fruit holding most of each detector segment's fruit pixels (fruit_segment_pairs), 0 for
    segments on no fruit."""
    owner = np.zeros(n_segments, np.int64)
    _, first = np.unique(seg, return_index=True)     # each segment's first, largest pair
    owner[seg[first]] = fruit[first]
    return owner


def clear_off_sphere(inst: np.ndarray, segments: np.ndarray | None, depth: np.ndarray, k: np.ndarray,
                     c2w: np.ndarray, spheres: dict[int, tuple[np.ndarray, float]], margin_m: float,
                     factor: float, split_min_px: int = 0) -> int:
    """Clear each pixel of a fused frame (`inst` [H, W] fruit ids, changed in place) whose fruit has a sphere
    and whose point (z-depth `depth` in m, intrinsics k = (fx, fy, cx, cy), pose c2w) lies farther than
    factor x radius + margin_m from that sphere's centre, unless a detector segment (`segments` [H, W] ids,
    0 = none; None = no detector output) whose fruit pixels are mostly this fruit's covers it and the point
    does not lie behind the sphere (more than radius + margin_m beyond its centre along the pixel's ray): a
    detector mask reaching past its fruit's outline onto a fruit or leaf further back does not keep those
    pixels on its fruit. A segment most of whose covered pixels lie behind the sphere is another fruit the
    render painted with this fruit's id: it keeps them all where the detector split can give them an id of
    their own (at least split_min_px of them, its min_px; 0 = no split). Fruits without a sphere keep their
    pixels. Returns the pixels cleared."""
    if factor <= 0 or not spheres:
        return 0
    ids, centres, radii = sphere_arrays(spheres)
    column = np.full(max(int(inst.max()), int(ids.max())) + 1, -1)   # fruit id -> its sphere (-1: none)
    column[ids] = np.arange(len(ids))
    v, u = np.nonzero((inst > 0) & (depth > 0))
    own = column[inst[v, u]]
    v, u, own = v[own >= 0], u[own >= 0], own[own >= 0]
    if not len(v):
        return 0
    p = unproject(depth, k, c2w, v, u)
    off = np.linalg.norm(p - centres[own], axis=1) > radii[own] * factor + margin_m
    if segments is not None and off.any():
        sid = segments[v, u]
        owner = segment_owners(*fruit_segment_pairs(inst, segments), int(segments.max()) + 1)
        vouched = (sid > 0) & (owner[sid] == inst[v, u])
        behind = beyond_centre(p, c2w[:3, 3], centres[own]) > radii[own] + margin_m
        # per segment, the pixels it vouches for and the share of them that lie behind their fruit's sphere
        n = np.bincount(sid[vouched], minlength=len(owner))
        share = np.bincount(sid[vouched], weights=behind[vouched], minlength=len(owner)) / np.maximum(n, 1)
        whole = (share >= 0.5) & (n >= split_min_px) & (split_min_px > 0)   # another fruit, left for the split
        off &= ~(vouched & (~behind | whole[sid]))
    inst[v[off], u[off]] = 0
    return int(off.sum())


def border_surfaces(inst: np.ndarray, depth: np.ndarray, k: np.ndarray, c2w: np.ndarray,
                    spheres: dict[int, tuple[np.ndarray, float]], clouds: dict[int, cKDTree], margin_m: float,
                    band_px: int) -> int:
    """Within `band_px` pixels of the edges of a fused frame (`inst` [H, W] fruit ids, changed in place), give
    each pixel whose point (z-depth `depth` in m, intrinsics k = (fx, fy, cx, cy), pose c2w) lies within
    margin_m of a fruit's seen surface (`clouds`, surface_clouds) to that fruit, unless the pixel's own fruit's
    surface holds it too. Where several fruits' surfaces hold a point, the nearest wins. Only pixels inside
    the image box of a fruit's sphere (`spheres`) are tested. A leaf beside a fruit, in front of it or behind
    it is not taken. Returns the pixels given a fruit or moved to another."""
    h, w = inst.shape
    band_px = min(band_px, w // 2)
    spheres = {f: b for f, b in spheres.items() if f in clouds}
    if margin_m <= 0 or band_px <= 0 or not spheres:
        return 0
    bh = min(band_px, h // 2)
    ids, centres, radii = sphere_arrays(spheres)
    boxes = sphere_boxes(inst.shape, k, c2w, centres, radii + margin_m)
    near = np.array([b is None or (b[0] < b[1] and b[2] < b[3]      # boxes reaching into the band
                                   and (b[0] < bh or b[1] > h - bh or b[2] < band_px or b[3] > w - band_px))
                     for b in boxes])
    if not near.any():
        return 0
    ids = ids[near]
    # only pixels in a sphere's box can see its surface: the band's pixels inside the near boxes
    edge = np.zeros((h, w), bool)
    edge[:, :band_px] = edge[:, w - band_px:] = True
    edge[:bh] = edge[h - bh:] = True
    boxes = [b for b, keep in zip(boxes, near) if keep]
    if all(b is not None for b in boxes):
        inside = np.zeros((h, w), bool)
        for v0, v1, u0, u1 in boxes:
            inside[v0:v1, u0:u1] = True
        edge &= inside
    v, u = np.nonzero(edge & (depth > 0))
    if not len(v):
        return 0
    column = np.full(max(int(inst.max()), int(ids.max())) + 1, -1)   # fruit id -> its column here (-1: none)
    column[ids] = np.arange(len(ids))
    p = unproject(depth, k, c2w, v, u)
    gap = np.full((len(p), len(ids)), np.inf)                          # [P, S] distance to each fruit's surface
    for j, (f, b) in enumerate(zip(ids.tolist(), boxes)):
        mine = np.ones(len(v), bool) if b is None else (v >= b[0]) & (v < b[1]) & (u >= b[2]) & (u < b[3])
        if mine.any():
            gap[mine, j] = clouds[f].query(p[mine], distance_upper_bound=margin_m)[0]
    rows = np.arange(len(p))
    best = gap.argmin(1)
    own = column[inst[v, u]]
    on_own = (own >= 0) & np.isfinite(gap[rows, np.maximum(own, 0)])
    ok = np.isfinite(gap[rows, best]) & ~on_own & (best != own)
    inst[v[ok], u[ok]] = ids[best[ok]]
    return int(ok.sum())


def fill_from_detector(inst: np.ndarray, segments: np.ndarray, depth: np.ndarray, k: np.ndarray, c2w: np.ndarray,
                       spheres: dict[int, tuple[np.ndarray, float]], margin_m: float) -> int:
    """Give each fruit of a fused frame (`inst` [H, W] fruit ids, changed in place) the pixels of its detector
    segment (`segments` [H, W] ids, 0 = none) that carry no fruit and whose point (z-depth `depth` in m,
    intrinsics k = (fx, fy, cx, cy), pose c2w) lies within its sphere (radius + margin_m), at most margin_m
    beyond the sphere's centre along the pixel's ray, and deeper in it (distance / radius) than in any other
    of `spheres`. The fruit's own surface faces the camera, in front of the centre; a leaf a little behind the
    fruit's outline lies near the sphere but behind the centre, so it is not taken. A fruit's segment: the
    one holding most of its pixels, provided that segment holds more of this fruit's pixels than of any other
    fruit's (a segment the detector spread over two fruits feeds only the fruit it covers most). Returns the
    pixels filled."""
    if margin_m <= 0 or not spheres:
        return 0
    fruit, seg = fruit_segment_pairs(inst, segments)
    if not len(fruit):
        return 0
    owner = segment_owners(fruit, seg, int(segments.max()) + 1)
    _, first = np.unique(fruit, return_index=True)   # each fruit's first, largest pair: the segment holding most of it
    seg_of = dict(zip(fruit[first].tolist(), seg[first].tolist()))
    ids, centres, radii = sphere_arrays(spheres)
    # each segment feeds at most one fruit, so the free pixels (no fruit, a segment, a depth) are found once
    free_v, free_u = np.nonzero((inst == 0) & (segments > 0) & (depth > 0))
    free_seg = segments[free_v, free_u]
    filled = 0
    for f, s in seg_of.items():
        if owner[s] != f or f not in spheres:
            continue
        mine = free_seg == s
        if not mine.any():
            continue
        v, u = free_v[mine], free_u[mine]
        p = unproject(depth, k, c2w, v, u)
        rel = np.linalg.norm(p[:, None] - centres[None], axis=2) / radii
        own = int(np.searchsorted(ids, f))
        past = beyond_centre(p, c2w[:3, 3], centres[own])
        ok = (rel[:, own] <= 1.0 + margin_m / radii[own]) & (past <= margin_m) & (rel.argmin(1) == own)
        inst[v[ok], u[ok]] = f
        filled += int(ok.sum())
    return filled


def regrow_hidden(inst: np.ndarray, depth: np.ndarray, k: np.ndarray, c2w: np.ndarray,
                  spheres: dict[int, tuple[np.ndarray, float]], clouds: dict[int, cKDTree], margin_m: float,
                  min_px: int) -> int:
    """Give back to each fruit of `spheres` (the fruits in view in this fused frame: surface_rules) the
    stuff pixels of the frame (`inst` [H, W] fruit ids, changed in place; 0 = stuff) whose point (z-depth
    `depth` in m, intrinsics k = (fx, fy, cx, cy), pose c2w) lies within margin_m of its seen surface
    (`clouds`, surface_clouds) and at most margin_m beyond its sphere's centre along the pixel's ray, where there
    are at least min_px of them and more than the fruit's own pixels inside its sphere's image box: the render
    hid most of what the sensor measures of the fruit (a glimpse between leaves, painted as leaf). A fruit the
    render paints well keeps its outline: the leaf along it is not taken. Where two fruits' surfaces hold a
    pixel, the nearer takes it. Returns the pixels given."""
    spheres = {f: b for f, b in spheres.items() if f in clouds}
    if margin_m <= 0 or min_px <= 0 or not spheres:
        return 0
    ids, centres, radii = sphere_arrays(spheres)
    boxes = sphere_boxes(inst.shape, k, c2w, centres, radii + margin_m)
    h, w = inst.shape
    taken_v, taken_u, taken_d, taken_f = [], [], [], []
    for f, c, b in zip(ids.tolist(), centres, boxes):
        v0, v1, u0, u1 = (0, h, 0, w) if b is None else b
        if v0 >= v1 or u0 >= u1:
            continue
        box = inst[v0:v1, u0:u1]
        v, u = np.nonzero((box == 0) & (depth[v0:v1, u0:u1] > 0))
        if len(v) < min_px:
            continue
        v, u = v + v0, u + u0
        p = unproject(depth, k, c2w, v, u)
        gap = clouds[f].query(p, distance_upper_bound=margin_m)[0]
        on = np.isfinite(gap) & (beyond_centre(p, c2w[:3, 3], c) <= margin_m)
        n = int(on.sum())
        if n >= min_px and n > np.count_nonzero(box == f):
            taken_v.append(v[on]), taken_u.append(u[on]), taken_d.append(gap[on]), taken_f.append(np.full(n, f))
    if not taken_v:
        return 0
    v, u, gap, f = (np.concatenate(a) for a in (taken_v, taken_u, taken_d, taken_f))
    order = np.argsort(gap, kind="stable")
    _, first = np.unique((v * w + u)[order], return_index=True)   # each pixel to the nearest surface
    pick = order[first]
    inst[v[pick], u[pick]] = f[pick]
    return len(pick)


def surface_rules(inst: np.ndarray, segments: np.ndarray | None, depth: np.ndarray, k: np.ndarray,
                  c2w: np.ndarray, spheres: dict[int, tuple[np.ndarray, float]], clouds: dict[int, cKDTree],
                  off_sensor: dict[int, np.ndarray], cfg: Config, ctx: StageContext,
                  painted: set[int] | None = None) -> None:
    """track_margin_m (relabel_by_surface), off_sphere_factor (clear_off_sphere, not for the fruits in
    `off_sensor`: render_off_sensor), detector_fill (fill_from_detector, where the frame has detector
    segments), border_band_px (border_surfaces; the spheres of the fruits in `off_sensor` moved by their
    offset, as their `clouds` are: moved_surfaces) and regrow_min_px (regrow_hidden, for the fruits in
    `painted`: those whose slots paint them at or before this frame and at or after it, and those the rules
    before it left with pixels in the frame; None = not run) on one fused frame (`inst` changed in place;
    cleared pixels get fruit id 0, which the callers map to background), their pixels counted in the summary."""
    moved = relabel_by_surface(inst, depth, k, c2w, spheres, cfg.track_margin_m)
    if moved:
        ctx.count("pixels_moved_to_their_surface", moved)
    judged = {f: ball for f, ball in spheres.items() if f not in off_sensor}
    cleared = clear_off_sphere(inst, segments, depth, k, c2w, judged, cfg.track_margin_m, cfg.off_sphere_factor,
                               cfg.min_group_px if cfg.detector_split_m > 0 else 0)
    if cleared:
        ctx.count("pixels_cleared_off_their_sphere", cleared)
    if cfg.detector_fill and segments is not None:
        filled = fill_from_detector(inst, segments, depth, k, c2w, spheres, cfg.track_margin_m)
        if filled:
            ctx.count("pixels_filled_from_detector", filled)
    at_sensor = {f: (c + off_sensor[f], r) if f in off_sensor else (c, r) for f, (c, r) in spheres.items()}
    if cfg.border_band_px:
        band = int(np.ceil(cfg.border_band_px * np.sqrt(max(1.0, inst.size / BASE_PIXELS)) - 1e-9))
        moved = border_surfaces(inst, depth, k, c2w, at_sensor, clouds, cfg.track_margin_m, band)
        if moved:
            ctx.count("pixels_given_at_the_border", moved)
    if cfg.regrow_min_px and painted is not None:
        # a fruit the earlier rules put in this frame outside its slots' span (a view its windows painted as
        # leaf or as a neighbour, which its surface won back) is as much in view as one its slots paint
        shown = painted | set(np.unique(inst[inst > 0]).tolist())
        given = regrow_hidden(inst, depth, k, c2w, {f: at_sensor[f] for f in shown if f in at_sensor}, clouds,
                              cfg.track_margin_m, image_pixels_for(cfg.regrow_min_px, inst.size))
        if given:
            ctx.count("pixels_regrown_where_hidden", given)


def segment_centres(inst: np.ndarray, segments: np.ndarray, depth: np.ndarray, k: np.ndarray, c2w: np.ndarray,
                    min_px: int, max_points: int) -> list[tuple[int, int, int, np.ndarray, np.ndarray]]:
    """(fruit id, segment id, pixels, centre [3], points [n, 3]) for each detector segment of a fused frame that
    lies mostly (over half of its pixels) on fused fruits, given to the fruit of `inst` that holds most of it,
    where that fruit holds at least min_px of its pixels with a depth: the centre is the robust median of
    their points (z-depth `depth` in m, intrinsics k, pose c2w), `points` at most max_points of them (evenly
    subsampled). A segment mostly on stuff is the detector's alone (a false detection, or a fruit the render
    does not show)."""
    on_fruit = (inst > 0) & (segments > 0)
    if not on_fruit.any():
        return []
    size = np.bincount(segments.ravel())
    covered = np.bincount(segments[on_fruit], minlength=len(size))
    v, u = np.nonzero(on_fruit & (depth > 0))
    if not len(v):
        return []
    key = inst[v, u].astype(np.int64) * len(size) + segments[v, u]      # one number per (fruit, segment)
    v, u, key, starts, ends = runs_by_key(v, u, key)
    out, taken = [], set()
    for j in np.argsort(-(ends - starts), kind="stable"):
        f, sid = divmod(int(key[starts[j]]), len(size))
        n = int(ends[j] - starts[j])
        if n < min_px or sid in taken or 2 * covered[sid] <= size[sid]:
            continue
        taken.add(sid)
        pts = unproject(depth, k, c2w, v[starts[j]:ends[j]], u[starts[j]:ends[j]])
        out.append((f, sid, n, robust_centre(pts)[0], pts[subsample(n, max_points)]))
    return out


def detector_clusters(views: list[tuple], link_m: float, min_frames: int,
                      off_fruit: Callable[[np.ndarray], bool | None] | None = None
                      ) -> tuple[np.ndarray, list[np.ndarray]]:
    """The fruits one fused fruit holds by its detector segments. `views`: (frame, segment, pixels, centre, ...)
    of the segments given to it (segment_centres). Centres closer than link_m are linked (single linkage); a
    cluster counts when seen in at least min_frames frames, and is a fruit of its own when it and another
    such cluster are seen together (in one frame) in at least min_frames frames. `off_fruit(centre)` says
    whether a centre lies off the fused fruit (outside its sphere: True, inside: False; None where the fruit
    has no plausible sphere): two clusters seen together in fewer frames (at least one) are two fruits too
    where the smaller one is not on the fruit (True or None), and a cluster off the fruit's sphere (True) is a
    fruit of its own beside the largest cluster even where they never share a frame. 3D evidence in place of
    repeated sightings, for a fruit the recording's first or last frames show once or twice. Returns (the
    cluster of each view, -1 for none; the clusters' centres, the one with most pixels first), or (all -1, [])
    where the segments show one fruit."""
    labels = np.full(len(views), -1)
    if link_m <= 0 or len(views) < 2:
        return labels, []
    pts = np.stack([v[3] for v in views])
    raw = fcluster(linkage(pts, "single"), link_m, criterion="distance")
    frames_of = defaultdict(set)
    for (f, *_), c in zip(views, raw):
        frames_of[c].add(f)
    px = {c: sum(v[2] for v, r in zip(views, raw) if r == c) for c in frames_of}
    lasting = {c for c, fs in frames_of.items() if len(fs) >= min_frames}
    off = {c: None if off_fruit is None else off_fruit(np.median(pts[raw == c], 0)) for c in frames_of}
    largest = max(frames_of, key=px.get)
    together = set()
    for a in frames_of:
        for b in frames_of:
            if a >= b:
                continue
            shared = len(frames_of[a] & frames_of[b])
            if a in lasting and b in lasting and shared >= min_frames:
                together |= {a, b}
            elif off_fruit is not None and ((shared and off[min(a, b, key=px.get)] is not False)
                                            or (largest in (a, b) and off[a if b == largest else b] is True)):
                together |= {a, b}
    if not together:
        return labels, []
    order = sorted(together, key=lambda c: -px[c])
    centres = [np.median(pts[raw == c], 0) for c in order]
    rank = {c: i for i, c in enumerate(order)}
    labels = np.array([rank.get(c, -1) for c in raw])
    return labels, centres


def split_by_detector(inst: np.ndarray, segments: np.ndarray, depth: np.ndarray, k: np.ndarray, c2w: np.ndarray,
                      fruit: int, ids: list[int], spheres: list[tuple[np.ndarray, float]] | None,
                      seg_cluster: dict[int, int], min_px: int, surfaces: list[cKDTree] | None = None,
                      margin_m: float = 0.0) -> int:
    """Hand a fused fruit's pixels of one frame (`inst`, changed in place) to the fruits it holds: the pixels of
    a detector segment of a cluster (`seg_cluster`: segment id -> index into `ids`) go to that cluster's id.
    Its other pixels with a depth that lie within margin_m of a cluster's seen surface (`surfaces`: k-d trees
    of each cluster's segments' points; None = not used) go to the cluster whose surface lies nearest: the
    sliver of a fruit entering the view before the detector shows it, which may lie inside a larger
    neighbour's sphere (spheres fitted to elongated fruits seen from one side overlap). The rest go to the id
    of the sphere (centre, radius; `spheres`) they lie deepest in (distance / radius), and a cluster without a
    segment in the frame that would get fewer than min_px pixels in all leaves those its sphere gave it to the
    first (stray pixels near a fruit that is not in view). Without spheres (`spheres` None), the rest go to
    the cluster whose seen surface lies nearest where that cluster has a segment in the frame, else to the
    first. Returns the pixels moved."""
    if spheres is None and surfaces is None:
        raise ValueError("split_by_detector needs the clusters' spheres or their seen surfaces")
    mine = inst == fruit
    target = np.full(inst.shape, -1)
    for sid, j in seg_cluster.items():
        target[mine & (segments == sid)] = j
    v, u = np.nonzero(mine & (target < 0) & (depth > 0))
    shown = set(seg_cluster.values())
    if len(v):
        p = unproject(depth, k, c2w, v, u)
        on_surface = np.zeros(len(v), bool)
        if surfaces is not None:
            gap = np.stack([tree.query(p)[0] for tree in surfaces], axis=1)
            on_surface = gap.min(1) <= margin_m
        if spheres is None:
            near = gap.argmin(1)
            near[~np.isin(near, list(shown)) & ~on_surface] = 0
        else:
            centres = np.stack([c for c, _ in spheres])
            radii = np.array([r for _, r in spheres])
            near = (np.linalg.norm(p[:, None] - centres[None], axis=2) / radii).argmin(1)
            if on_surface.any():
                near[on_surface] = gap[on_surface].argmin(1)
            for j in range(1, len(ids)):
                if j not in shown and np.count_nonzero(near == j) < min_px:
                    near[(near == j) & ~on_surface] = 0
        target[v, u] = near
    new = np.where(target >= 0, np.asarray(ids)[np.maximum(target, 0)], inst)
    moved = int(np.count_nonzero(mine & (new != fruit)))
    inst[mine] = new[mine]
    return moved


def fused_labels(renders: Renders, wid: int, fid: int, shape: tuple[int, int], groups_px: dict,
                 lut: dict[tuple[int, int, int], int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(semantic uint8, instance uint16 row-level fruit ids, depth m) of one window's render of a frame, its
    slots' pixel groups mapped to fused fruits through `lut`; pixels of dropped slots become void."""
    sem, inst, depth = read_render(renders, wid, fid, shape)
    thing = np.isin(sem, THING_IDS) & (inst > 0)
    out_inst = np.zeros(inst.shape, np.uint16)
    out_sem = sem.astype(np.uint8)
    group = np.zeros(inst.shape, np.int64)
    if (wid, fid) in groups_px:
        flat, g = groups_px[(wid, fid)]
        group.ravel()[flat] = g
    codes = code(inst.astype(np.int64), group)
    for c in np.unique(codes[thing]):
        m = thing & (codes == c)
        fruit_id = lut.get((wid, fid, int(c)), 0)
        if fruit_id:
            out_inst[m] = fruit_id
        else:
            out_sem[m] = VOID
    return out_sem, out_inst, depth


def compose(labelled: list[tuple[np.ndarray, np.ndarray, np.ndarray]], wins: list[int],
            support: dict[tuple[int, int], tuple[int, int]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """One fused frame from the renders several windows made of it (`labelled`: fused_labels per window of
    `wins`, the nearest window first). Each fruit takes its pixels from the window that saw it best among
    those showing it here (most rendered frames, then pixels: `support` per (window, fruit)); a window that
    sees a fruit only while it enters or leaves the window's stretch of row renders it smaller or paints it
    with a neighbour's id. The nearest window's pixels win where two windows' chosen fruits overlap; pixels
    no chosen fruit covers take the semantic and depth of the first window that shows no fruit there (void
    where every window shows one). Returns (semantic, instance, depth, whether any pixel came from another
    window than the nearest)."""
    sem0, inst0, depth0 = labelled[0]
    if len(labelled) == 1:
        return sem0, inst0, depth0, False
    best: dict[int, int] = {}
    for j, (_, inst, _) in enumerate(labelled):
        for f in np.unique(inst[inst > 0]).tolist():
            s = support.get((wins[j], f), (0, 0))
            if f not in best or s > support.get((wins[best[f]], f), (0, 0)):
                best[f] = j
    src = np.full(inst0.shape, -1, np.int64)       # the window each pixel is taken from
    out_inst = np.zeros_like(inst0)
    for j, (_, inst, _) in enumerate(labelled):
        chosen = np.zeros(int(inst.max()) + 1, bool)
        chosen[[f for f, b in best.items() if b == j]] = True   # best[f] == j only for fruits window j shows
        m = (src < 0) & chosen[inst]
        out_inst[m] = inst[m]
        src[m] = j
    for j, (_, inst, _) in enumerate(labelled):
        m = (src < 0) & (inst == 0)
        src[m] = j
    out_sem = np.full(inst0.shape, VOID, np.uint8)
    depth = depth0.copy()
    for j, (sem, _, d) in enumerate(labelled):
        m = src == j
        out_sem[m] = sem[m]
        depth[m] = d[m]
    return out_sem, out_inst, depth, bool((src > 0).any())


def write_fused(out_dir: Path, name: str, sem: np.ndarray, inst: np.ndarray) -> None:
    """Write one fused frame's semantic (8-bit) and instance (16-bit) PNGs under `out_dir`. The label arrays
    may be int32 (read_label); cv2 would write those as 8-bit, turning every fruit id past 255 into 255."""
    write_png(out_dir / "semantic" / name, sem.astype(np.uint8))
    write_png(out_dir / "instance" / name, inst.astype(np.uint16))


def split_fruits(seg_views: dict, in_frame: dict[int, set[int]], depth_file: dict[int, Path],
                 cams: dict[int, np.ndarray], rows: list[dict], spheres: dict, clouds: dict[int, cKDTree],
                 off_sensor: dict[int, np.ndarray], fruit_centres: dict[int, np.ndarray], fruit_class: np.ndarray,
                 frames: pd.DataFrame, dropped: dict, out_dir: Path, cfg: Config, ctx: StageContext
                 ) -> tuple[int, dict[int, tuple[np.ndarray, float]], dict[int, np.ndarray], np.ndarray]:
    """detector_split_m: rewrite the fused frames (PNGs in `out_dir`; per frame its depth PNG `depth_file` and
    pose `cams`) of the fruits the detector shows as several (detector_clusters on `seg_views`: per fruit its
    (frame, segment, pixels, centre, points)); `rows` (panoptic_frames rows) get their fruit counts updated.
    A split-off cluster joins the nearest fruit whose centre (`fruit_centres`: sphere centres, else the
    association's) lies within max_match_distance_m of its own (its sphere's centre where the fit is
    plausible) or inside its sphere (radius + track_margin_m), or whose sphere holds its centre; else it is a
    new fruit. Where every cluster has a plausible sphere, the fruit, new fruits and joined fruits without a
    sphere take their cluster's (and its segments' points inside it as their surface, `clouds`), and the
    surface rules run again with them (a fruit given its cluster's sphere leaves `off_sensor`: that sphere is
    fitted to sensor points). `dropped`: the segments the depth filter dropped, per frame. Returns the number of
    fruits of the row, and their spheres, render offsets (`off_sensor`) and classes (fruit id -> class) after
    the split."""
    plans = {}
    classes = list(fruit_class)
    n_fruits = len(fruit_class) - 1
    sphere_of = dict(spheres)
    cloud_of = dict(clouds)
    off_sensor = dict(off_sensor)
    known = sorted(fruit_centres)
    known_xyz = np.stack([fruit_centres[g] for g in known]) if known else np.zeros((0, 3))
    for f, views in sorted(seg_views.items()):
        ball = spheres.get(f)
        labels, centres = detector_clusters(
            views, cfg.detector_split_m, cfg.min_split_frames,
            lambda c: None if ball is None else float(np.linalg.norm(c - ball[0])) > ball[1] + cfg.track_margin_m)
        if not centres:
            continue
        seen = [np.concatenate([v[4] for v, lab in zip(views, labels) if lab == j]) for j in range(len(centres))]
        fits = [fruit_sphere(pts, cfg.max_fruit_radius_m) for pts in seen]   # each cluster's segments' points
        ids = [f]
        for j in range(1, len(centres)):
            at = fits[j][0] if fits[j] is not None else centres[j]
            reach = max(cfg.max_match_distance_m, fits[j][1] + cfg.track_margin_m if fits[j] is not None else 0.0)
            dist = np.linalg.norm(known_xyz - at, axis=1)
            near = [(d, g) for d, g in zip(dist, known) if g != f and g not in ids and (
                d <= reach or (g in spheres and d <= spheres[g][1] + cfg.track_margin_m))]
            if near:
                ids.append(min(near)[1])
            else:
                n_fruits += 1
                ids.append(n_fruits)
                classes.append(classes[f])
        seg_cluster: dict[int, dict[int, int]] = defaultdict(dict)
        for (fid, sid, *_), lab in zip(views, labels):
            if lab >= 0:
                seg_cluster[fid][sid] = int(lab)
        if all(fit is not None for fit in fits):
            balls = [(fit[0], float(fit[1])) for fit in fits]
            for j, (g, ball) in enumerate(zip(ids, balls)):
                if j == 0 or g not in spheres:   # a sphere for this fruit, new fruits and hosts without one
                    sphere_of[g] = ball
                    off_sensor.pop(g, None)   # fitted to its segments' sensor points
                    cloud_of.pop(g, None)
                    cloud_of.update(seen_surfaces({g: seen[j]}, {g: ball}, cfg))
        else:
            balls = None
        surfaces = [cKDTree(pts) for pts in seen]   # each cluster's seen surface: its segments' points
        plans[f] = (ids, balls, seg_cluster, surfaces)
        ctx.count("fruits_split_by_detector")
    if not plans:
        return n_fruits, spheres, off_sensor, fruit_class
    if n_fruits > 65535:
        raise ValueError(f"panoptic_fusion: {n_fruits} fruits do not fit 16-bit instance PNGs (max 65535)")
    fruit_class = np.asarray(classes, np.uint8)
    split = set(plans)
    for row in ctx.progress([r for r in rows if in_frame[r["frame_id"]] & split], "split fruits"):
        fid = row["frame_id"]
        fr = frames.loc[fid]
        name = f"{fid:06d}.png"
        sem = read_label(out_dir / "semantic" / name, "fused semantic")
        inst = read_label(out_dir / "instance" / name, "fused instance")
        depth = placed_depth(depth_file[fid], fr, cfg, ctx)
        segments = fruit_segments(fr, ctx.data_root, dropped.get(fid))
        k = np.array([fr.fx, fr.fy, fr.cx, fr.cy], np.float64)
        c2w = cams[fid]
        before = inst.copy()
        for f in sorted(in_frame[fid] & split):
            ids, balls, seg_cluster, surfaces = plans[f]
            moved = split_by_detector(inst, segments, depth, k, c2w, f, ids, balls, seg_cluster.get(fid, {}),
                                      cfg.min_group_px, surfaces, cfg.track_margin_m)
            ctx.count("pixels_moved_by_detector_split", moved)
        if sphere_of:   # with the clusters' spheres: pieces without a sphere of their own join them
            surface_rules(inst, segments, depth, k, c2w, sphere_of, cloud_of, off_sensor, cfg, ctx)
        m = inst != before
        sem[m] = fruit_class[inst[m]]
        write_fused(out_dir, name, sem, inst)
        row["n_fruits"] = int(len(np.unique(inst[inst > 0])))
    return n_fruits, sphere_of, off_sensor, fruit_class


def placed_depth(depth_path: Path, fr, cfg: Config, ctx: StageContext) -> np.ndarray:
    """[H, W] metres: a fused frame's depth (its PNG at `depth_path`; `fr` its frames row) as the surface rules
    place pixels with it (surface_depth: the recorded depth where valid, or the render's)."""
    depth = read_depth(depth_path)
    if cfg.surface_depth == "sensor":
        depth = with_sensor_depth(depth, ctx.abspath(fr.depth_path), fr.depth_scale_m)
    return depth


def regrow_on_fused(rows: list[dict], depth_file: dict[int, Path], cams: dict[int, np.ndarray],
                    points: dict[int, np.ndarray], spheres: dict[int, tuple[np.ndarray, float]],
                    off_sensor: dict[int, np.ndarray], fruit_class: np.ndarray, frames: pd.DataFrame,
                    out_dir: Path, cfg: Config, ctx: StageContext) -> None:
    """regrow_passes after the first, on the written fused frames (PNGs in `out_dir`; `rows` their
    panoptic_frames rows, `depth_file` and `cams` their depth PNG and pose): each pass grows the seen surface
    of each fruit in `spheres` but not in `off_sensor` from its render points (`points`: fruit_points) and the
    points of the pixels it holds in every fused frame (max_points_per_view per frame), then runs
    regrow_hidden on every frame for the fruits in view there: those the fused frames show from the frame
    before the first that shows them to the frame after the last (a fruit the fused frames lose for a frame or
    two behind a leaf, or one frame before it is first shown as it enters the view), rewriting the frames it
    changes (semantic from `fruit_class`, the rows' fruit counts). A fruit of `points` without a sphere (its
    render points fit no plausible one: a cap seen from one side) joins with the sphere its grown points fit,
    where they fit one."""
    judged = {f: ball for f, ball in spheres.items() if f not in off_sensor}
    unfitted = [f for f in points if f not in spheres and f not in off_sensor]
    if not cfg.regrow_min_px or not (judged or unfitted):
        return

    def fused_frame(row: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        fr = frames.loc[row["frame_id"]]
        inst = read_label(out_dir / "instance" / f"{row['frame_id']:06d}.png", "fused instance")
        return inst, placed_depth(depth_file[row["frame_id"]], fr, cfg, ctx), np.array([fr.fx, fr.fy, fr.cx, fr.cy])

    for n in range(2, cfg.regrow_passes + 1):
        grown: dict[int, list[np.ndarray]] = {f: [points[f]] if f in points else [] for f in [*judged, *unfitted]}
        shown: dict[int, list[int]] = {}   # fruit -> [first, last] position in `rows` of a frame showing it
        for at, row in enumerate(ctx.progress(rows, f"regrow pass {n}: seen surfaces")):
            inst, depth, k = fused_frame(row)
            for f in np.unique(inst[inst > 0]).tolist():
                shown.setdefault(f, [at, at])[1] = at
            v, u = np.nonzero((inst > 0) & (depth > 0))
            v, u, ids, starts, ends = runs_by_key(v, u, inst[v, u])
            for s0, s1 in zip(starts.tolist(), ends.tolist()):
                if int(ids[s0]) in grown:
                    pick = s0 + subsample(s1 - s0, cfg.max_points_per_view)
                    grown[int(ids[s0])].append(unproject(depth, k, cams[row["frame_id"]], v[pick], u[pick]))
        grown_points = {f: np.concatenate(p) for f, p in grown.items() if p}
        judged.update(fruit_spheres({f: grown_points[f] for f in unfitted if f in grown_points},
                                    cfg.max_fruit_radius_m))
        unfitted = [f for f in unfitted if f not in judged]
        clouds = seen_surfaces(grown_points, judged, cfg)
        for at, row in enumerate(ctx.progress(rows, f"regrow pass {n}")):
            inst, depth, k = fused_frame(row)
            in_view = {f: ball for f, ball in judged.items() if f in shown and shown[f][0] - 1 <= at <= shown[f][1] + 1}
            before = inst.copy()
            given = regrow_hidden(inst, depth, k, cams[row["frame_id"]], in_view, clouds, cfg.track_margin_m,
                                  image_pixels_for(cfg.regrow_min_px, inst.size))
            if given:
                row["n_fruits"] = int(len(np.unique(inst[inst > 0])))
                ctx.count("pixels_regrown_on_grown_surfaces", given)
                name = f"{row['frame_id']:06d}.png"
                sem = read_label(out_dir / "semantic" / name, "fused semantic")
                m = inst != before
                sem[m] = fruit_class[inst[m]]
                write_fused(out_dir, name, sem, inst)


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    frames: pd.DataFrame = inputs["frames"].set_index("frame_id", drop=False)
    renders = Renders(inputs["renders"], ctx.data_root)
    views = window_views(inputs["windows"], inputs["window_poses"], inputs["window_metrics"], renders, ctx)
    if cfg.align_windows and not views.empty:
        wp = inputs["window_poses"]
        align = window_alignments(wp[wp.window_id.isin(views.window_id.unique())])
        views["c2w"] = [align[int(w)] @ c for w, c in zip(views.window_id, views.c2w)]
        moved = max(float(np.linalg.norm(t[:3, 3])) for t in align.values())
        ctx.summary["window_alignment_max_m"] = round(moved, 4)
    out_dir = ctx.output_dir("panoptic")
    (out_dir / "semantic").mkdir(parents=True, exist_ok=True)
    (out_dir / "instance").mkdir(parents=True, exist_ok=True)
    if views.empty:
        ctx.note("no window has panoptic renders: nothing fused, tables are empty")
        ctx.summary.update(frames=0, fruits=0)
        return {"panoptic_frames": schemas.empty("panoptic_frames"), "fruit_slots": schemas.empty("fruit_slots")}
    missing = sorted(set(views.frame_id.astype(int)) - set(frames.index.astype(int)))
    if missing:
        raise ValueError(f"panoptic_fusion: window_poses/windows list frames {missing[:10]} that are not in "
                         f"frames.parquet; rerun the pipeline from ingest")
    shared = views.groupby("frame_id").window_id.nunique()
    shared_frames = set(shared[shared > 1].index.astype(int))
    n_cls = max(THING_IDS) + 1

    # pass 1: per (window, slot, frame) pixel groups (split where their 3D points lie apart), with their pixel
    # counts, classes and world points
    slot_views: dict[tuple[int, int], dict[tuple[int, int], SlotView]] = defaultdict(dict)
    gap_check = cfg.surface_depth == "sensor" and cfg.off_sphere_factor > 0 and cfg.track_margin_m > 0
    masks: dict[tuple[int, int], np.ndarray] = {}
    groups_px: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}  # (pixel index, group > 0) per view
    for r in ctx.progress(views.itertuples(index=False), "read renders", total=len(views)):
        wid, fid = int(r.window_id), int(r.frame_id)
        fr = frames.loc[fid]
        sem, inst, depth = read_render(renders, wid, fid, (int(fr.height), int(fr.width)))
        thing = np.isin(sem, THING_IDS) & (inst > 0)
        group = np.zeros(inst.shape, np.int32)
        if not thing.any():
            if fid in shared_frames:
                masks[(wid, fid)] = group
            continue
        v, u = np.nonzero(thing)
        v, u, ids, starts, ends = runs_by_key(v, u, inst[v, u])
        k = np.array([fr.fx, fr.fy, fr.cx, fr.cy], np.float64)
        sensor = (with_sensor_depth(np.zeros_like(depth), ctx.abspath(fr.depth_path), fr.depth_scale_m)
                  if gap_check else None)   # 0 where the sensor has no depth
        for s0, s1 in zip(starts, ends):
            vv, uu = v[s0:s1], u[s0:s1]
            good = depth[vv, uu] > 0
            pts = unproject(depth, k, r.c2w, vv[good], uu[good])
            labels = np.zeros(len(vv), np.int64)
            labels[good] = pixel_groups(vv[good], uu[good], pts, cfg.group_gap_m, cfg.min_group_px, MAX_GROUPS)
            group[vv, uu] = labels
            if labels.any():
                ctx.count("views_with_slot_groups")
            for g in range(int(labels.max()) + 1):
                mine = labels == g
                pts_g = pts[labels[good] == g]
                cls = np.bincount(sem[vv[mine], uu[mine]], minlength=n_cls)[:n_cls]
                pts_g = pts_g[subsample(len(pts_g), cfg.max_points_per_view)]
                gap, offset = np.nan, None
                if sensor is not None:
                    both = mine & good & (sensor[vv, uu] > 0)
                    if both.any():
                        vb, ub = vv[both], uu[both]
                        gap = float(np.median(depth[vb, ub] - sensor[vb, ub]))
                        sel = subsample(len(vb), cfg.max_points_per_view)   # their rendered points are in pts
                        offset = np.median(unproject(sensor, k, r.c2w, vb[sel], ub[sel]) - pts[both[good]][sel], 0)
                slot_views[(wid, int(ids[s0]))][(fid, g)] = SlotView(int(mine.sum()), cls, pts_g, gap, offset,
                                                                     r.c2w[:3, 3])
        if fid in shared_frames:
            masks[(wid, fid)] = np.where(thing, code(inst, group), 0).astype(np.int32)
        flat = np.flatnonzero(group)
        if len(flat):
            groups_px[(wid, fid)] = (flat, group.ravel()[flat])

    # pass 2: window-local fruits (slots, split where the centres of their per-frame groups disagree)
    local: list[LocalFruit] = []
    unfitted: list[tuple[LocalFruit, np.ndarray, np.ndarray]] = []  # (fruit, points, mean eye) without a sphere
    radii: list[float] = []
    for (wid, slot), per_frame in sorted(slot_views.items()):
        centres = {f: (np.median(sv.points, 0) if len(sv.points) else None) for f, sv in per_frame.items()}
        parts = split_frames(centres, cfg.split_distance_m, cfg.min_split_frames)
        if len(parts) > 1:
            ctx.count("slots_split")
        for p, fids in enumerate(parts):
            svs = [per_frame[f] for f in fids]
            n_px = sum(sv.n_px for sv in svs)
            pts = np.concatenate([sv.points for sv in svs])
            cls = int(np.argmax(sum(sv.class_px for sv in svs)))
            lf = LocalFruit(wid, slot, p, fids, n_px, cls, None)
            if n_px < cfg.min_slot_px:
                lf.drop_reason = f"{n_px} px < min_slot_px {cfg.min_slot_px}"
            elif len(pts) == 0:
                lf.drop_reason = "no pixel with valid rendered depth"
            else:
                fit = fruit_sphere(pts, cfg.max_fruit_radius_m, min_points=20) if cfg.centre == "sphere" else None
                lf.median = fit[2] if fit is not None else robust_centre(pts)[0]   # fruit_sphere's own median
                lf.centre = lf.median
                if fit is not None:
                    lf.centre = fit[0]
                    radii.append(fit[1])
                elif cfg.centre == "sphere":
                    eye = np.average([sv.eye for sv in svs], 0, [len(sv.points) for sv in svs])
                    unfitted.append((lf, pts, eye))
            local.append(lf)
    # a slot whose free sphere fit fails (a shallow or partial cap) takes a sphere of the row's median fitted
    # radius behind its seen part: its median lies on the side the window saw, centimetres from another
    # window's view of the same fruit
    if radii and unfitted:
        r_row = float(np.median(radii))
        for lf, pts, eye in unfitted:
            c = sphere_behind(pts, eye, r_row, min_points=20)
            if c is not None:
                lf.centre = c
                ctx.count("slots_centred_behind_their_surface")

    # pass 3: associate across windows; row-level ids increase along the row (x, then z; fruits split off by
    # detector_split_m follow)
    groups = associate(local, masks, cfg)
    gcentre = [np.median(np.stack([local[i].centre for i in g]), 0) for g in groups]
    order = sorted(range(len(groups)), key=lambda j: (gcentre[j][0], gcentre[j][2], gcentre[j][1]))
    if len(order) > 65535:
        raise ValueError(f"panoptic_fusion: {len(order)} fruits do not fit 16-bit instance PNGs (max 65535)")
    for fruit_id, j in enumerate(order, start=1):
        for i in groups[j]:
            local[i].fruit_id = fruit_id
    fruit_class = np.zeros(len(groups) + 1, np.uint8)   # fruit id -> class with the most pixels (0 -> background)
    for g in groups:
        px = defaultdict(int)
        for i in g:
            px[local[i].class_id] += local[i].n_px
        fruit_class[local[g[0]].fruit_id] = max(px, key=px.get)
    spheres, clouds, off_sensor, points = {}, {}, {}, {}
    if cfg.track_margin_m > 0:
        points = fruit_points(groups, local, slot_views)
        spheres = fruit_spheres(points, cfg.max_fruit_radius_m)
        clouds = seen_surfaces(points, spheres, cfg)
        if cfg.regrow_passes == 1:
            points = {}
        off_sensor = render_off_sensor(spheres, fruit_render_gaps(groups, local, slot_views), cfg)
        ctx.count("spheres_off_the_sensor_depth", len(off_sensor))
        clouds = moved_surfaces(clouds, off_sensor)
    dropped = [lf for lf in local if lf.fruit_id == 0]
    ctx.count("slots", len(local))
    ctx.count("slots_dropped", len(dropped))
    lut: dict[tuple[int, int, int], int] = {}  # (window, frame, slot code) -> fruit
    for lf in local:
        for f, g in lf.frames:
            lut[(lf.window_id, f, code(lf.slot, g))] = lf.fruit_id

    # pass 4: one fused panoptic image per frame, from the window whose centre is nearest; in a frame several
    # windows rendered, each fruit takes its pixels from the window that saw it best (compose_shared_frames)
    support: dict[tuple[int, int], tuple[int, int]] = {}  # (window, fruit) -> (frames, pixels) over its renders
    for lf in local:
        if lf.fruit_id:
            n_f, n_px = support.get((lf.window_id, lf.fruit_id), (0, 0))
            support[(lf.window_id, lf.fruit_id)] = (n_f + len({f for f, _ in lf.frames}), n_px + lf.n_px)
    dropped = dropped_segments(inputs.get("detections_filtered"))
    pick = views.assign(abs_off=views.offset.abs()).sort_values(["frame_id", "abs_off", "window_id"])
    n_win = views.groupby("frame_id").window_id.nunique()
    split = cfg.detector_split_m > 0
    seg_views: dict[int, list[tuple]] = defaultdict(list)  # fruit -> (frame, *segment_centres) of its segments
    in_frame: dict[int, set[int]] = {}   # frame -> the fruits in its fused image
    depth_file: dict[int, Path] = {}     # frame -> its fused depth PNG
    cams: dict[int, np.ndarray] = {}     # frame -> camera pose (row frame)
    spans: dict[int, tuple[int, int]] = {}   # fruit -> (first, last) frame its slots paint it in
    for lf in local:
        if lf.fruit_id and lf.frames:
            lo, hi = min(f for f, _ in lf.frames), max(f for f, _ in lf.frames)
            first, last = spans.get(lf.fruit_id, (lo, hi))
            spans[lf.fruit_id] = (min(first, lo), max(last, hi))
    rows = []
    for fid, frame_views in ctx.progress(pick.groupby("frame_id", sort=True), "write fused frames",
                                         total=int(pick.frame_id.nunique())):
        fid = int(fid)
        fr = frames.loc[fid]
        r = next(frame_views.itertuples(index=False))
        wid = int(r.window_id)
        shape = (int(fr.height), int(fr.width))
        wins = [int(w) for w in frame_views.window_id] if cfg.compose_shared_frames else [wid]
        labelled = [fused_labels(renders, w, fid, shape, groups_px, lut) for w in wins]
        out_sem, out_inst, depth, composed = compose(labelled, wins, support)
        depth_path = renders.relpath(wid, fid, "depth")
        if composed:
            ctx.count("frames_composed_from_several_windows")
            depth_path = ctx.relpath("panoptic", f"depth/{fid:06d}.png")
            (out_dir / "depth").mkdir(exist_ok=True)
            write_png(out_dir / "depth" / f"{fid:06d}.png", encode("depth", depth))
        k = np.array([fr.fx, fr.fy, fr.cx, fr.cy], np.float64)
        placed = depth
        if cfg.surface_depth == "sensor" and (spheres or split):
            placed = with_sensor_depth(depth, ctx.abspath(fr.depth_path), fr.depth_scale_m)
        segments = None
        if ((cfg.detector_fill or cfg.off_sphere_factor) and spheres) or split:
            segments = fruit_segments(fr, ctx.data_root, dropped.get(fid))
        if spheres:
            before = out_inst.copy()
            painted = {f for f, (first, last) in spans.items() if first <= fid <= last}
            surface_rules(out_inst, segments, placed, k, r.c2w, spheres, clouds, off_sensor, cfg, ctx, painted)
            m = out_inst != before
            out_sem[m] = fruit_class[out_inst[m]]
        if split and segments is not None:
            for f, *view in segment_centres(out_inst, segments, placed, k, r.c2w, cfg.min_group_px,
                                            cfg.max_points_per_view):
                seg_views[f].append((fid, *view))
        present = np.unique(out_inst[out_inst > 0])
        in_frame[fid] = set(present.tolist())
        depth_file[fid] = out_dir / "depth" / f"{fid:06d}.png" if composed else ctx.abspath(depth_path)
        cams[fid] = r.c2w
        name = f"{fid:06d}.png"
        write_fused(out_dir, name, out_sem, out_inst)
        rows.append({"frame_id": fid, "stamp_ns": int(fr.stamp_ns), "window_id": wid, "offset": int(r.offset),
                     "n_windows": int(n_win[fid]),
                     "semantic_path": ctx.relpath("panoptic", f"semantic/{name}"),
                     "instance_path": ctx.relpath("panoptic", f"instance/{name}"),
                     "rgb_path": renders.relpath(wid, fid, "rgb"),
                     "depth_path": depth_path,
                     "n_fruits": len(present),
                     **dict(zip(POSE_COLS, pose_txyzq(r.c2w[None])[0].tolist()))})
    n_fruits = len(groups)
    if seg_views:
        centres = {local[g[0]].fruit_id: (spheres[local[g[0]].fruit_id][0] if local[g[0]].fruit_id in spheres
                                          else gcentre[j]) for j, g in enumerate(groups)}
        n_fruits, spheres, off_sensor, fruit_class = split_fruits(
            seg_views, in_frame, depth_file, cams, rows, spheres, clouds, off_sensor, centres, fruit_class, frames,
            dropped, out_dir, cfg, ctx)
    if cfg.regrow_passes > 1:
        regrow_on_fused(rows, depth_file, cams, points, spheres, off_sensor, fruit_class, frames, out_dir, cfg, ctx)
    slots = pd.DataFrame([{
        "window_id": lf.window_id, "slot": lf.slot, "part": lf.part, "fruit_id": lf.fruit_id,
        "class_id": lf.class_id, "n_frames": len({f for f, _ in lf.frames}), "n_px": lf.n_px,
        "x_m": None if lf.centre is None else float(lf.centre[0]),
        "y_m": None if lf.centre is None else float(lf.centre[1]),
        "z_m": None if lf.centre is None else float(lf.centre[2]),
        "drop_reason": lf.drop_reason} for lf in local], columns=schemas.get("fruit_slots").names)
    ctx.summary.update(windows=int(views.window_id.nunique()), frames=len(rows), fruits=n_fruits,
                       frames_in_several_windows=len(shared_frames))
    return {"panoptic_frames": pd.DataFrame(rows, columns=schemas.get("panoptic_frames").names),
            "fruit_slots": slots}
