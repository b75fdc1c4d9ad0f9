"""Locate, size, classify and count every fused fruit; write the fruit table, counts and a fruit point cloud."""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
from scipy.optimize import least_squares
from scipy.stats import binom

import schemas
from nerf.geometry import pose_matrix
from pipeline.classes import DEFAULT_CLASSES, THING_IDS, class_name
from pipeline.images import ImageError, read_label
from pipeline.parallel import available_cores, in_order
from pipeline.stage import StageContext
from nerf.surfaces import fit_sphere, plausible_fit, principal_extents, robust_centre, runs_by_key, unproject
from rowmap.colours import id_colours
from rowmap.detections import dropped_segments
from rowmap.ends import MIN_SPAN_FRAMES, Track, end_tracks
from rowmap.geometry import subsample, with_sensor_depth
from rowmap.renders import read_depth
from rowmap.scoring import reference_pixels
from rowmap.structure import VoxelCloud, frame_points

INPUTS = ("frames", "nerf", "panoptic_frames", "panoptic", "fruit_slots", "images", "detections_filtered")
OUTPUTS = ("fruits", "counts", "fruit_map", "structure")


@dataclass(frozen=True)
class Config:
    max_depth_m: float = 1.5
    """metres, > 0. Fruits whose median viewing depth is beyond this are the far row: near_row = false, not
    counted. Keep it equal to depth_filter.max_depth_m; set it from the row spacing (between the near row's
    far side and the next row)."""
    mad_k: float = 3.0
    """> 0. Outlier test: a point is rejected when its distance to the fruit's median exceeds
    median + mad_k * 1.4826 * MAD of those distances (a robust 3-sigma at 3). Lower it when leaves or the next
    fruit bleed into the masks' depth, raise it when small fruits lose too many points."""
    diameter_method: Literal["spheroid", "sphere", "pca"] = "spheroid"
    """what diameter_m reports: a least-squares fit to the visible surface of a spheroid with a vertical axis
    ('spheroid': a hanging fruit such as a pepper is about a body of revolution, taller than wide), of a
    sphere ('sphere': its radius mixes width and length, so it reads high on elongated fruits), or the
    principal extents of the points ('pca': a half-seen surface is smaller than the fruit, so it reads low).
    All three are written to fruits.parquet; 'sphere' suits round fruits (tomatoes, apples)."""
    surface_depth: Literal["sensor", "rendered"] = "sensor"
    """the depth each fused fruit pixel is un-projected with for the fruit's centre, size and median depth:
    'sensor' = the recorded depth image where it has a valid pixel (the rendered depth elsewhere),
    'rendered' = the NeRF's depth everywhere. The render is weakest at the image border and in the frames
    at a window's ends, where it can place a fruit entering or leaving the view centimetres from its
    surface; the sensor measures that surface. Use 'rendered' for a depth sensor that is noisier on fruits
    than the render (the render averages the depth of many frames) or with holes over most fruits."""
    min_points: int = 20
    """points, >= 4: fruits with fewer 3D points get no size (diameter null) and the median as centre."""
    max_points_per_view: int = 600
    """points, >= 1: 3D points kept per fruit and frame (evenly subsampled); lower it on large images to save
    time."""
    max_radius_m: float = 0.15
    """metres, > 0. A surface fit with a larger radius, or a centre farther than this from the points'
    median, is rejected (a nearly flat patch); without any fit the fruit gets the median as centre and the
    PCA diameter. Set it above the largest fruit radius of the crop."""
    min_count_frames: int = 2
    """fused frames, >= 1. A fruit seen in fewer is a fragment (a stray piece of a slot, a one-frame
    duplicate): listed in fruits.parquet with counted = false, not counted. 1 = count every fruit seen."""
    min_count_points: int = 100
    """points, >= 0: a fruit with fewer 3D points over the row is a fragment too (counted = false); so is one
    with fewer pixels with depth (surface_depth) over its fused frames, each frame's pixels counted as in a
    320x180 image (nerf.config.BASE_PIXELS; x 1/16 at 1280x720). The second part keeps the rule's meaning at
    every image size: a fruit covers 16 times the pixels at 1280x720, and its points are capped per frame
    (max_points_per_view). Up to 320x180 it is implied by the first."""
    lone_fragment_m: float = 0.06
    """metres, >= 0 (0 = off). A fragment (min_count_frames, min_count_points) is counted after all when the
    detector confirms it in every fused frame it is seen in, it has at least min_points points, and no counted
    fruit lies within this distance of its centre: a fruit seen only in the first or last frames of the
    recording is a fragment by size, and so is a stray piece of a fruit already counted, but the piece lies
    next to that fruit. Fragments closer than this to each other count once (the one with most points). About
    the smallest distance between two fruits' centres (a fruit diameter)."""
    duplicate_within_m: float = 0.03
    """metres, >= 0 (0 = off). Two counted fruits whose centres lie closer are one fruit under two ids (a window
    painted it with two slots where no other window saw it): the one with fewer points is not counted. Two fruits'
    centres lie at least the sum of their radii apart; keep it under the crop's smallest fruit radius."""
    max_count_diameter_m: float = 0.15
    """metres, > 0. A fruit whose measured diameter (diameter_m) exceeds this is not one fruit but pieces of
    several, or of a fruit and what lies behind it, under one id (most often a slot a window paints while
    fruits enter or leave its first or last frames): listed in fruits.parquet with counted = false. Set it
    about 1.5 times the largest fruit diameter of the crop; a very large value switches the rule off. Fruits
    without a size (diameter null) are not affected."""
    detector_cover: float = 0.3
    """share in (0, 1]: a fused frame confirms a fruit when the detector's thing segments of that frame cover at
    least this share of the fruit's pixels there (the detector is not the NeRF's input on validation frames, so
    it is an independent witness). Lower it for detectors with tight or partial masks."""
    detector_alpha: float = 0.05
    """probability in [0, 1); 0 = off. A fruit is unconfirmed (counted = false) when it is confirmed in under
    half the share of frames the row's fruits are confirmed in on average (the detector's recall r) AND, were
    it real, so few confirmations out of its n frames would have a chance under this (binomial:
    P(X <= k | n, r)). That is what the NeRF renders from a detector false positive in a few training frames,
    which the validation frames' detections never repeat. The level bounds how short-lived a phantom can be
    and still be caught: with r = 0.9 a fruit confirmed in none of 2 frames has P = 0.01, of 3 frames 0.001;
    with r = 0.8, 0.04 and 0.008. A fruit whose points admit no plausible surface fit (no fruit shape: a
    patch of leaf the render paints as fruit, or pieces of several things) is unconfirmed on the first test
    alone: without shape evidence the detector has to confirm it in at least half the row's share of
    frames, however few frames it is seen in. Lower it to drop fewer fruits, 0 with a detector that misses
    fruits in many frames (0 switches both tests off)."""
    end_tracks: bool = True
    """count the fruits the detector alone tracks where no two fused frames see them: a recording's ends, a failed
    window's frames (rowmap.ends, linked within lone_fragment_m / 2; end_fruits; off too at lone_fragment_m 0)."""
    max_fit_extent_ratio: float = 2.0
    """>= 1. A surface fit whose diameter (or length) exceeds this multiple of the largest extent of the points
    is rejected too: it extrapolates a whole fruit from a small cap (a fruit seen only as a sliver over or past
    another one), where a seen half of a fruit spans about its full diameter. Lower it (towards 1.3) when
    occluded fruits get oversized diameters; raise it when fruits seen from one side only lose their fit."""

    def __post_init__(self) -> None:
        if not self.max_depth_m > 0:
            raise ValueError(f"fruit_count.max_depth_m must be > 0, got {self.max_depth_m}")
        if not self.mad_k > 0:
            raise ValueError(f"fruit_count.mad_k must be > 0, got {self.mad_k}")
        if not self.lone_fragment_m >= 0:
            raise ValueError(f"fruit_count.lone_fragment_m must be >= 0, got {self.lone_fragment_m}")
        if not self.duplicate_within_m >= 0:
            raise ValueError(f"fruit_count.duplicate_within_m must be >= 0, got {self.duplicate_within_m}")
        if self.min_count_frames < 1 or self.min_count_points < 0:
            raise ValueError("fruit_count.min_count_frames must be >= 1 and min_count_points >= 0")
        if self.min_points < 4 or self.max_points_per_view < 1:
            raise ValueError("fruit_count.min_points must be >= 4 (a sphere has 4 parameters) and "
                             "max_points_per_view >= 1")
        if not self.max_count_diameter_m > 0:
            raise ValueError(f"fruit_count.max_count_diameter_m must be > 0, got {self.max_count_diameter_m}")
        if not self.max_radius_m > 0:
            raise ValueError(f"fruit_count.max_radius_m must be > 0, got {self.max_radius_m}")
        if not 0 < self.detector_cover <= 1 or not 0 <= self.detector_alpha < 1:
            raise ValueError("fruit_count.detector_cover must be in (0, 1] and detector_alpha in [0, 1)")
        if not self.max_fit_extent_ratio >= 1:
            raise ValueError(f"fruit_count.max_fit_extent_ratio must be >= 1, got {self.max_fit_extent_ratio}")


def fit_spheroid(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares spheroid with a vertical (z) axis through points [N, 3] (N >= 5):
    ((x-cx)^2 + (y-cy)^2) / a^2 + (z-cz)^2 / c^2 = 1. Algebraic start from the linear model
    A (x^2 + y^2) + C z^2 + D x + E y + F z = 1, then the normalised radial residual (|.| - 1) * min(a, c)
    minimised with a soft-L1 loss. Returns (centre [3], equatorial diameter 2a, polar length 2c);
    NaN where the fit degenerates (e.g. a flat patch)."""
    p = np.asarray(points, np.float64)
    mu = p.mean(0)
    q = p - mu
    a_mat = np.c_[q[:, 0] ** 2 + q[:, 1] ** 2, q[:, 2] ** 2, q]
    (ka, kc, d, e, f), *_ = np.linalg.lstsq(a_mat, np.ones(len(q)), rcond=None)
    nan = (np.full(3, np.nan), np.nan, np.nan)
    if not (ka > 0 and kc > 0):
        return nan
    c0 = np.array([-d / (2 * ka), -e / (2 * ka), -f / (2 * kc)])
    g = 1 + ka * (c0[0] ** 2 + c0[1] ** 2) + kc * c0[2] ** 2
    if not g > 0:
        return nan
    x0 = np.r_[c0, np.sqrt(g / ka), np.sqrt(g / kc)]

    def resid(x: np.ndarray) -> np.ndarray:
        rho = np.sqrt(((q[:, 0] - x[0]) ** 2 + (q[:, 1] - x[1]) ** 2) / x[3] ** 2 + (q[:, 2] - x[2]) ** 2 / x[4] ** 2)
        return (rho - 1) * min(abs(x[3]), abs(x[4]))

    x = least_squares(resid, x0, loss="soft_l1", f_scale=0.003, max_nfev=100).x
    return x[:3] + mu, 2 * abs(float(x[3])), 2 * abs(float(x[4]))


def is_fragment(n_frames: int, n_points: int, ref_pixels: float, cfg: Config) -> bool:
    """A fruit seen in under cfg.min_count_frames fused frames, or with under cfg.min_count_points inlier points
    or reference pixels (reference_pixels summed over its fused frames): not counted."""
    return n_frames < cfg.min_count_frames or min(n_points, ref_pixels) < cfg.min_count_points


def spaced(fruits: pd.DataFrame, ids: list[int], taken: list[np.ndarray], min_distance_m: float) -> list[int]:
    """Of fruit `ids` (rows of `fruits`: fruit_id, x_m, y_m, z_m, n_points), most points first (ties: the lower
    id), those whose centre lies farther than min_distance_m from every centre in `taken` and every id taken before."""
    by_id = fruits.set_index("fruit_id")
    taken, out = list(taken), []
    for f in sorted(ids, key=lambda f: (-int(by_id.n_points[f]), f)):
        p = by_id.loc[f, ["x_m", "y_m", "z_m"]].to_numpy(np.float64)
        if all(np.linalg.norm(p - q) > min_distance_m for q in taken):
            out.append(f)
            taken.append(p)
    return out


def lone_fragments(fruits: pd.DataFrame, candidates: list[int], min_distance_m: float) -> list[int]:
    """The candidate fruit ids (fragments the detector confirms in every frame) to count after all: taken by
    points, most first, each only if no counted fruit of `fruits` (fruit_id, x_m, y_m, z_m, counted, n_points)
    and no candidate taken before lies within min_distance_m of its centre (0 = none)."""
    if min_distance_m <= 0 or not candidates:
        return []
    counted = fruits.loc[fruits.counted.astype(bool), ["x_m", "y_m", "z_m"]].to_numpy(np.float64)
    return spaced(fruits, candidates, list(counted), min_distance_m)


def duplicates(fruits: pd.DataFrame, within_m: float) -> list[int]:
    """The counted fruits of `fruits` (fruit_id, x_m, y_m, z_m, counted, n_points) whose centre lies within
    `within_m` of a counted fruit with more points (ties: the lower id is kept); [] at 0."""
    if within_m <= 0:
        return []
    counted = fruits.loc[fruits.counted.astype(bool), "fruit_id"].astype(int).tolist()
    return sorted(set(counted) - set(spaced(fruits, counted, [], within_m)))


def majority_class(votes: np.ndarray) -> int:
    """The class most votes name, among the thing classes where any vote names one."""
    things = votes[np.isin(votes, THING_IDS)]
    return int(np.bincount(things if len(things) else votes).argmax())


def has_shape(m: dict) -> bool:
    """Whether measure's result `m` has a plausible sphere or spheroid fit (a fruit's shape)."""
    return m["diameter_sphere_m"] is not None or m["diameter_spheroid_m"] is not None


def end_tracks_on(cfg: Config) -> bool:
    """Whether the end tracks are counted: end_tracks, and a lone_fragment_m to link them within."""
    return cfg.end_tracks and cfg.lone_fragment_m > 0


def end_fruits(tracks: list[Track], fruits: pd.DataFrame, cfg: Config) -> list[tuple[Track, dict]]:
    """The end tracks (rowmap.ends) to count as fruits, with measure's result: seen in at least min_count_frames
    frames over at least MIN_SPAN_FRAMES, not a fragment by points or pixels, in the near row, not oversize, and
    apart from every counted fruit of `fruits` and every track taken before (most points first): farther than
    lone_fragment_m and than the sum of the two radii (two fruits do not overlap; a segment merging two fruits
    measures wide and lies between them). No surface fit is asked for: a fruit at a recording's end is seen as a
    shallow cap at the image border, which fits none, and a track is the detector's in each of its frames, the
    confirmation a fused fruit without a fit needs (detector_support)."""
    if not end_tracks_on(cfg):
        return []
    counted = fruits[fruits.counted.astype(bool)]
    taken = list(zip(counted[["x_m", "y_m", "z_m"]].to_numpy(np.float64),
                     counted.diameter_m.fillna(0.0).to_numpy(np.float64) / 2))
    out = []
    for t in sorted(tracks, key=lambda t: -sum(map(len, t.points))):
        if len(t.frames) < cfg.min_count_frames or t.span < MIN_SPAN_FRAMES:
            continue
        m = measure(np.concatenate(t.points), cfg)
        near_row = float(np.median(np.concatenate(t.depths))) <= cfg.max_depth_m
        fragment = is_fragment(len(t.frames), m["n_points"], sum(t.ref_px), cfg)
        if fragment or not near_row or oversize(m["diameter_m"], cfg):
            continue
        p, r = np.array([m["x_m"], m["y_m"], m["z_m"]], np.float64), (m["diameter_m"] or 0.0) / 2
        if all(np.linalg.norm(p - q) > max(cfg.lone_fragment_m, r + rq) for q, rq in taken):
            out.append((t, m))
            taken.append((p, r))
    return out


def end_fruit_rows(ends: list[tuple[Track, dict]], first_id: int) -> list[dict]:
    """The fruits.parquet rows of the end tracks to count (end_fruits), ids from first_id on: class by majority
    of the detector's segments, no fused frames (n_frames 0), end_track_frames the frames tracked."""
    rows = []
    for fruit, (t, m) in enumerate(ends, start=first_id):
        cls = np.asarray(t.classes)
        c = majority_class(cls)
        rows.append({"fruit_id": fruit, "class_id": c, "class_name": class_name(c),
                     "class_confidence": float(np.mean(cls == c)), **m,
                     "median_depth_m": float(np.median(np.concatenate(t.depths))), "near_row": True, "n_frames": 0,
                     "counted": True, "n_confirmed_frames": None, "detector_p": None, "n_windows": 0,
                     "first_frame_id": min(t.frames), "last_frame_id": max(t.frames),
                     "end_track_frames": len(t.frames)})
    return rows


def oversize(diameter_m: float | None, cfg: Config) -> bool:
    """A fruit measured wider than cfg.max_count_diameter_m: not one fruit, not counted (no size: not oversize)."""
    return diameter_m is not None and bool(np.isfinite(diameter_m)) and diameter_m > cfg.max_count_diameter_m


def measure(points: np.ndarray, cfg: Config) -> dict:
    """Centre, sizes and inlier counts of one fruit's world points [N, 3]."""
    med, keep = robust_centre(points, cfg.mad_k)
    inl = points[keep]
    out = {"x_m": med[0], "y_m": med[1], "z_m": med[2], "n_points": int(keep.sum()),
           "n_outliers": int((~keep).sum()), "diameter_m": None, "diameter_spheroid_m": None, "diameter_sphere_m": None,
           "diameter_pca_m": None, "axis1_m": None, "axis2_m": None, "axis3_m": None, "height_m": None}
    if len(inl) < cfg.min_points:
        return out
    ext = principal_extents(inl)
    out.update(axis1_m=ext[0], axis2_m=ext[1], axis3_m=ext[2], diameter_pca_m=ext[1],
               height_m=float(np.percentile(inl[:, 2], 97.5) - np.percentile(inl[:, 2], 2.5)))

    def plausible(c: np.ndarray, r: float) -> bool:
        return plausible_fit(c, r, med, ext[0], cfg.max_radius_m, cfg.max_fit_extent_ratio)

    centres = {}
    c, r = fit_sphere(inl)
    if plausible(c, r):
        centres["sphere"] = c
        out["diameter_sphere_m"] = 2 * r
    c, dia, length = fit_spheroid(inl)
    if plausible(c, max(dia, length) / 2):
        centres["spheroid"] = c
        out["diameter_spheroid_m"] = dia
    chosen = cfg.diameter_method if cfg.diameter_method != "pca" else "spheroid"
    centre = centres.get(chosen, centres.get("spheroid", centres.get("sphere")))
    if centre is not None:  # a surface fit's centre; the median of the seen surface is biased towards the camera
        out.update(x_m=centre[0], y_m=centre[1], z_m=centre[2])
    out["diameter_m"] = out[f"diameter_{cfg.diameter_method}_m"]
    if out["diameter_m"] is None:
        fallbacks = [out["diameter_spheroid_m"], out["diameter_sphere_m"], out["diameter_pca_m"]]
        out["diameter_m"] = next(v for v in fallbacks if v is not None)
    return out


def detector_support(checked: dict[int, int], confirmed: dict[int, int], alpha: float,
                     shapeless: frozenset[int] | set[int] = frozenset()) -> dict[int, tuple[float, bool]]:
    """Per fruit with n = checked[f] > 0 frames of which k = confirmed[f] confirm it: (p, unconfirmed), with
    r = the pooled confirmation rate over all fruits, p = P(X <= k) for X ~ Binomial(n, r) (the chance a real
    fruit is confirmed this rarely) and unconfirmed = k / n < r / 2 and (p < alpha or f in shapeless), for
    alpha > 0. The first test keeps a well-confirmed fruit under a detector that confirms nearly everything
    (the pooled rate makes the binomial overconfident: occluded fruits are missed more often than the
    average). The binomial gives a fruit seen in few frames the benefit of the doubt; a shapeless fruit (its
    points admit no plausible surface fit) has no 3D evidence of being a fruit, so it gets none."""
    n_all = sum(checked.values())
    if not n_all:
        return {}
    rate = min(sum(confirmed.get(f, 0) for f in checked) / n_all, 1.0)
    out = {}
    for f, n in checked.items():
        k = confirmed.get(f, 0)
        p = float(binom.cdf(k, n, rate))
        out[f] = (p, bool(alpha > 0 and k / n < rate / 2 and (p < alpha or f in shapeless)))
    return out


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    import open3d as o3d

    frames: pd.DataFrame = inputs["frames"].set_index("frame_id", drop=False)
    pf: pd.DataFrame = inputs["panoptic_frames"]
    slots: pd.DataFrame = inputs["fruit_slots"]
    points: dict[int, list[np.ndarray]] = defaultdict(list)
    votes: dict[int, list[int]] = defaultdict(list)
    depths: dict[int, list[np.ndarray]] = defaultdict(list)
    seen: dict[int, list[int]] = defaultdict(list)
    ref_px: dict[int, float] = defaultdict(float)  # pixels with depth, scaled to a BASE_PIXELS image
    checked: dict[int, int] = defaultdict(int)      # fused frames with a detector image, per fruit
    confirmed: dict[int, int] = defaultdict(int)    # ... of them where the detector's segments cover the fruit

    structure = VoxelCloud()                        # the row's stuff surfaces, for registering dates

    def unproject_frame(r) -> tuple[int, list[tuple], tuple[np.ndarray, np.ndarray]]:
        """Fused frame r's fruits (on a worker thread): (frame id, [(fruit, reference pixels with depth, whether
        the detector covers it (None: no detector image), its majority class, its depths, its points)], the
        frame's stuff points and classes)."""
        fid = int(r.frame_id)
        if fid not in frames.index:
            raise ValueError(f"fruit_count: panoptic_frames frame {fid} is not in frames.parquet")
        fr = frames.loc[fid]
        inst = read_label(ctx.abspath(r.instance_path), "fused instance")
        sem = read_label(ctx.abspath(r.semantic_path), "fused semantic")
        depth = read_depth(ctx.abspath(r.depth_path))
        if not inst.shape == sem.shape == depth.shape:
            raise ImageError(f"frame {fid}: fused PNGs {r.instance_path} {inst.shape}, {r.semantic_path} {sem.shape} "
                             f"and depth render {r.depth_path} {depth.shape} differ in size")
        if cfg.surface_depth == "sensor":
            depth = with_sensor_depth(depth, ctx.abspath(fr.depth_path), fr.depth_scale_m)
        det = None
        if "det_instance_path" in fr.index and isinstance(fr.det_instance_path, str) and fr.det_instance_path:
            det = read_label(ctx.abspath(fr.det_instance_path), "detector instance")
            if det.shape != inst.shape:
                raise ImageError(f"frame {fid}: detector instance PNG {fr.det_instance_path} {det.shape} and fused "
                                 f"PNG {r.instance_path} {inst.shape} differ in size")
        c2w = pose_matrix(np.array([r.tx, r.ty, r.tz, r.qx, r.qy, r.qz, r.qw], np.float64))  # row frame
        k = np.array([fr.fx, fr.fy, fr.cx, fr.cy], np.float64)
        v, u = np.nonzero(inst > 0)
        v, u, ids, starts, ends = runs_by_key(v, u, inst[v, u])
        found = []
        for s0, s1 in zip(starts, ends):
            vv, uu = v[s0:s1], u[s0:s1]
            d = depth[vv, uu]
            good = d > 0
            covered = None if det is None else bool(np.mean(det[vv, uu] > 0) >= cfg.detector_cover)
            pts = None
            if good.any():
                pick = subsample(int(good.sum()), cfg.max_points_per_view)
                pts = unproject(depth, k, c2w, vv[good][pick], uu[good][pick])
            found.append((int(ids[s0]), float(reference_pixels(int(good.sum()), inst.size)), covered,
                          int(np.bincount(sem[vv, uu]).argmax()), d[good], pts))
        return fid, found, frame_points(depth, sem, k, c2w, cfg.max_depth_m)

    read_all = in_order(unproject_frame, pf.itertuples(index=False), available_cores())
    for fid, found, stuff in ctx.progress(read_all, "unproject fruits", total=len(pf)):
        structure.add(*stuff)
        for fruit, px, covered, vote, d, pts in found:
            seen[fruit].append(fid)
            ref_px[fruit] += px
            if covered is not None:
                checked[fruit] += 1
                confirmed[fruit] += int(covered)
            votes[fruit].append(vote)
            if pts is not None:
                depths[fruit].append(d)
                points[fruit].append(pts)
    n_windows = slots[slots.fruit_id > 0].groupby("fruit_id").window_id.nunique()
    measured: dict[int, tuple[np.ndarray, dict]] = {}   # fruit -> (its points, measure's result)
    for fruit in ctx.progress(sorted(seen), "measure fruits", total=len(seen)):
        if fruit not in points:
            ctx.count("fruits_without_depth")
            ctx.note(f"fruit {fruit}: no pixel with valid depth in frames {seen[fruit]}; not in fruits")
            continue
        pts = np.concatenate(points[fruit])
        measured[fruit] = pts, measure(pts, cfg)
    shapeless = {f for f, (_, m) in measured.items() if not has_shape(m)}
    support = detector_support(checked, confirmed, cfg.detector_alpha, shapeless)
    rows, cloud_pts, cloud_ids = [], [], []
    too_wide: list[int] = []  # near-row fruits not counted by the oversize rule
    lone_candidates: list[int] = []  # fragments the detector confirms in every frame (lone_fragment_m)
    for fruit, (pts, m) in measured.items():
        v = np.asarray(votes[fruit])
        cls = majority_class(v)
        med_depth = float(np.median(np.concatenate(depths[fruit])))
        near_row, n_frames = med_depth <= cfg.max_depth_m, len(set(seen[fruit]))
        wide = oversize(m["diameter_m"], cfg)
        if near_row and wide:
            too_wide.append(fruit)
        p_real, unconfirmed = support.get(fruit, (None, False))
        eligible = near_row and not unconfirmed and not wide   # counted unless a fragment
        fragment = is_fragment(n_frames, m["n_points"], ref_px[fruit], cfg)
        if (eligible and fragment and m["n_points"] >= cfg.min_points
                and checked.get(fruit, 0) > 0 and confirmed.get(fruit, 0) == checked[fruit]):
            lone_candidates.append(fruit)
        rows.append({"fruit_id": fruit, "class_id": cls, "class_name": class_name(cls),
                     "class_confidence": float(np.mean(v == cls)), **m, "median_depth_m": med_depth,
                     "near_row": near_row, "n_frames": n_frames,
                     "counted": bool(eligible and not fragment),
                     "n_confirmed_frames": confirmed.get(fruit, 0) if fruit in checked else None,
                     "detector_p": p_real,
                     "n_windows": int(n_windows.get(fruit, 1)), "first_frame_id": min(seen[fruit]),
                     "last_frame_id": max(seen[fruit]), "end_track_frames": None})
        cloud_pts.append(pts)
        cloud_ids.append(np.full(len(pts), fruit))
    fruits = pd.DataFrame(rows, columns=schemas.get("fruits").names) if rows else schemas.empty("fruits")
    lone = lone_fragments(fruits, lone_candidates, cfg.lone_fragment_m)
    fruits.loc[fruits.fruit_id.isin(lone), "counted"] = True
    dups = duplicates(fruits, cfg.duplicate_within_m)
    fruits.loc[fruits.fruit_id.isin(dups), "counted"] = False
    tracks = end_tracks(frames, pf, ctx.data_root, dropped_segments(inputs.get("detections_filtered")),
                        cfg.lone_fragment_m / 2, cfg.max_points_per_view, cfg.min_points) if end_tracks_on(cfg) else []
    ends = end_fruits(tracks, fruits, cfg)
    added = end_fruit_rows(ends, int(max(fruits.fruit_id, default=0)) + 1)
    for r, (t, _) in zip(added, ends):
        cloud_pts.append(np.concatenate(t.points))
        cloud_ids.append(np.full(len(cloud_pts[-1]), r["fruit_id"]))
    if added:
        fruits = pd.concat([fruits, pd.DataFrame(added, columns=fruits.columns)], ignore_index=True)
    near = fruits[fruits.counted.astype(bool)]
    things = [(c, near[near.class_id == c.id]) for c in DEFAULT_CLASSES if c.is_thing]
    counts = pd.DataFrame([{"class_id": c.id, "class_name": c.name, "count": len(of_c),
                            "mean_diameter_m": float(of_c.diameter_m.mean()) if of_c.diameter_m.notna().any() else None}
                           for c, of_c in things], columns=schemas.get("counts").names)
    pcd = o3d.geometry.PointCloud()
    if cloud_pts:
        pcd.points = o3d.utility.Vector3dVector(np.concatenate(cloud_pts))
        pcd.colors = o3d.utility.Vector3dVector(id_colours(np.concatenate(cloud_ids)).astype(np.float64) / 255)
    ply = Path(ctx.output_dir("fruit_map")) / "fruits.ply"
    if not cloud_pts:  # Open3D refuses to write an empty cloud; an empty PLY is still a valid file
        ply.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty double x\nproperty double y\n"
                       "property double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
                       "end_header\n")
    elif not o3d.io.write_point_cloud(str(ply), pcd, write_ascii=False):
        raise OSError(f"fruit_count: open3d could not write {ply}")
    n_far = int((~fruits.near_row.astype(bool)).sum())
    if n_far:
        ctx.note(f"{n_far} fruits beyond {cfg.max_depth_m:g} m (far row) are in fruits.parquet with near_row = "
                 f"false and not counted")
    if too_wide:
        ctx.note(f"fruits {too_wide}: measured wider than "
                 f"{cfg.max_count_diameter_m:g} m (max_count_diameter_m), pieces of several fruits under one id: "
                 f"in fruits.parquet with counted = false")
    n_frag = int((fruits.near_row.astype(bool) & ~fruits.counted.astype(bool) & ~fruits.fruit_id.isin(dups)).sum())
    unconf = [f for f, (_, u) in support.items() if u]
    if unconf:
        ctx.note(f"fruits {unconf}: the detector confirms them in too few of their frames (detector_p < "
                 f"{cfg.detector_alpha:g}): in fruits.parquet with counted = false")
    if lone:
        ctx.note(f"fruits {lone}: fragments by size, confirmed by the detector in every frame and farther than "
                 f"{cfg.lone_fragment_m:g} m from any counted fruit (lone_fragment_m): counted")
    if dups:
        ctx.note(f"fruits {dups}: within {cfg.duplicate_within_m:g} m of a counted fruit with more points, the same "
                 f"fruit under a second id (duplicate_within_m): counted = false")
    if ends:
        ctx.note(f"fruits {[r['fruit_id'] for r in added]}: tracked by the detector where no two fused "
                 f"frames see them (the recording's ends, failed windows; end_tracks): counted, without fused pixels")
    if n_frag:
        ctx.note(f"{n_frag} near-row fruits not counted: fragments (under {cfg.min_count_frames} fused frames or "
                 f"under {cfg.min_count_points} points or pixels at 320x180), unconfirmed by the detector or wider "
                 f"than max_count_diameter_m; counted = false")
    ctx.summary.update(fruits=len(fruits), counted=len(near), far_row=n_far, fragments=n_frag, unconfirmed=len(unconf),
                       oversize=len(too_wide), lone_fragments=len(lone), duplicates=len(dups), end_fruits=len(ends),
                       **{f"count_{c}": int(n) for c, n in zip(counts.class_name, counts["count"])})
    table = structure.table()
    ctx.summary["structure_voxels"] = len(table)
    return {"fruits": fruits, "counts": counts, "structure": table}
