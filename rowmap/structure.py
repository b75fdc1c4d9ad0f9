"""The row's static structure: stems, leaves, floor and pipes as a voxel cloud, and how two clouds are aligned.

Fruits grow, ripen and are picked between recording dates; the rest of the row (the stems, the mass of the
leaves, the floor, the heating pipes) stays where it was, within the few centimetres a leaf moves. Each row
keeps that structure as the mean point of every occupied VOXEL_M voxel of its stuff pixels (fruit_count writes
it as `structure.parquet`), and a season registers its dates on it (rowmap/season/registration.py):

    coarse_shift        the translation that overlaps the two clouds' occupancy most (an FFT correlation of
                        COARSE_CELL_M grids), within the largest shift the robot's start and drift allow;
    align_yaw_shift     point-to-plane ICP restricted to x, y, z and yaw (the row frames are gravity-aligned),
                        with a shrinking inlier radius;
    local_offsets       the translation that aligns each stretch of the row on its own: the two odometries'
                        different drift, which no rigid transform removes.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from nerf.surfaces import unproject
from pipeline.classes import DEFAULT_CLASSES
from rowmap.geometry import subsample

VOXEL_M = 0.01
"""Edge of the structure's voxels (m): a centimetre keeps stems and leaf edges apart and a row of 10 m under
a few hundred thousand voxels."""
POINTS_PER_FRAME = 6000
"""Stuff pixels un-projected per frame (evenly subsampled): neighbouring frames overlap, so a few thousand
per frame fill the voxels a frame sees."""
COARSE_CELL_M = 0.03
"""Cell of the occupancy grids the coarse shift is correlated on (m): coarse enough to overlap clouds a leaf's
movement apart, fine enough to tell neighbouring stems."""
ICP_CELL_M = 0.02
"""Voxel the clouds are thinned to for the ICP (m), normals from the neighbours within five of them."""
MIN_POINTS = 200
"""Fewest thinned structure points a date needs to be registered on its structure (else on its fruits)."""
_STUFF = np.array([c.id for c in DEFAULT_CLASSES if not c.is_thing])
_KEY_BITS = 21   # voxel index bits per axis: +-10 km at 1 cm


def frame_points(depth_m: np.ndarray, semantic: np.ndarray, k: np.ndarray, c2w: np.ndarray, max_depth_m: float,
                 cap: int = POINTS_PER_FRAME) -> tuple[np.ndarray, np.ndarray]:
    """(points [N, 3] in the frame of c2w, their class ids [N]) of the stuff pixels (not fruit, not void) of one
    frame with depth in (0, max_depth_m], at most `cap` of them evenly spread. k = (fx, fy, cx, cy)."""
    ok = np.isin(semantic, _STUFF) & np.isfinite(depth_m) & (depth_m > 0) & (depth_m <= max_depth_m)
    v, u = np.nonzero(ok)
    pick = subsample(len(v), cap)
    v, u = v[pick], u[pick]
    return unproject(depth_m, k, c2w, v, u), semantic[v, u].astype(np.int32)


class VoxelCloud:
    """Running per-voxel means of points and counts of their stuff classes; memory grows with the occupied
    voxels, not with the frames added (pending points are folded in every `fold_every` points)."""

    def __init__(self, voxel_m: float = VOXEL_M, fold_every: int = 1_000_000):
        self.voxel_m, self.fold_every = voxel_m, fold_every
        self._keys = np.zeros(0, np.int64)
        self._sums = np.zeros((0, 3))
        self._votes = np.zeros((0, len(_STUFF)), np.int64)
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._n_pending = 0

    def add(self, xyz: np.ndarray, class_id: np.ndarray) -> None:
        """Points [N, 3] with their stuff class ids [N]."""
        self._pending.append((np.asarray(xyz, np.float64).reshape(-1, 3), np.asarray(class_id)))
        self._n_pending += len(xyz)
        if self._n_pending >= self.fold_every:
            self._fold()

    def _fold(self) -> None:
        if not self._pending:
            return
        xyz = np.concatenate([p for p, _ in self._pending])
        cls = np.concatenate([c for _, c in self._pending])
        self._pending, self._n_pending = [], 0
        half = 1 << (_KEY_BITS - 1)
        cell = np.floor(xyz / self.voxel_m).astype(np.int64) + half
        key = (cell[:, 0] << (2 * _KEY_BITS)) | (cell[:, 1] << _KEY_BITS) | cell[:, 2]
        votes = (cls[:, None] == _STUFF[None]).astype(np.int64)
        keys, inv = np.unique(np.concatenate([self._keys, key]), return_inverse=True)
        inv = inv.reshape(-1)
        sums = np.stack([np.bincount(inv, w, len(keys)) for w in np.concatenate([self._sums, xyz]).T], 1)
        all_votes = np.concatenate([self._votes, votes])
        self._votes = np.stack([np.bincount(inv, w, len(keys)) for w in all_votes.T], 1).astype(np.int64)
        self._keys, self._sums = keys, sums

    def table(self) -> pd.DataFrame:
        """One row per occupied voxel (schemas/structure.py): mean x_m, y_m, z_m, n_points, majority class_id."""
        self._fold()
        n = self._votes.sum(1)
        mean = self._sums / np.maximum(n, 1)[:, None]
        return pd.DataFrame({"x_m": mean[:, 0].astype(np.float32), "y_m": mean[:, 1].astype(np.float32),
                             "z_m": mean[:, 2].astype(np.float32), "n_points": n.astype(np.int32),
                             "class_id": _STUFF[self._votes.argmax(1)].astype(np.int32) if len(n) else
                             np.zeros(0, np.int32)})


def structure_of_frames(frames: pd.DataFrame, data_root: Path, max_depth_m: float, c2w: np.ndarray,
                        place: Callable[[np.ndarray], np.ndarray]) -> pd.DataFrame:
    """The structure table of a row from its frames table and given poses, for a row without fused frames
    (fruit_count uses the fused ones): each frame's recorded depth and its detector's semantic labels,
    un-projected with `c2w` [N, 4, 4] (one per frame), then through `place` (a function of points [M, 3]).
    Frames without a detector semantic image are skipped."""
    from pipeline.images import read_depth_m, read_label

    cloud = VoxelCloud()
    for i, r in enumerate(frames.itertuples(index=False)):
        if not isinstance(getattr(r, "det_semantic_path", None), str):
            continue
        depth = read_depth_m(Path(data_root) / r.depth_path, r.depth_scale_m)
        sem = read_label(Path(data_root) / r.det_semantic_path, "detector semantic")
        pts, cls = frame_points(depth, sem, np.array([r.fx, r.fy, r.cx, r.cy], np.float64), c2w[i], max_depth_m)
        cloud.add(place(pts), cls)
    return cloud.table()


@dataclass(frozen=True)
class Structure:
    """A date's structure, thinned for registration: points [N, 3] (row frame) and unit normals [N, 3]."""
    points: np.ndarray
    normals: np.ndarray

    @classmethod
    def from_points(cls, xyz: np.ndarray, cell_m: float = ICP_CELL_M) -> "Structure":
        from nerf.depth_poses import numpy_cloud

        c = numpy_cloud(np.asarray(xyz, np.float64).reshape(-1, 3), cell_m)
        return cls(c.points, c.normals)

    def __len__(self) -> int:
        return len(self.points)


def coarse_shift(moving: np.ndarray, fixed: np.ndarray, max_shift_m: float, max_dz_m: float = 0.15,
                 cell_m: float = COARSE_CELL_M) -> tuple[np.ndarray, float]:
    """(translation [3], share of moving cells it lands on fixed ones) that overlaps the occupancy of points
    `moving` [M, 3] with that of `fixed` [F, 3] most: the peak of their cross-correlation on a cell_m grid (one
    FFT), among the shifts within max_shift_m along the floor and max_dz_m in height."""
    from scipy.signal import fftconvolve

    lo = np.minimum(moving.min(0), fixed.min(0)) - cell_m
    hi = np.maximum(moving.max(0), fixed.max(0)) + cell_m
    bins = [np.arange(lo[a], hi[a] + cell_m, cell_m) for a in range(3)]
    a_occ = (np.histogramdd(fixed, bins)[0] > 0).astype(np.float32)
    b_occ = (np.histogramdd(moving, bins)[0] > 0).astype(np.float32)
    corr = fftconvolve(a_occ, b_occ[::-1, ::-1, ::-1], mode="full")          # index k: shift k - (n - 1) cells
    shape = np.array(b_occ.shape)
    sx, sy, sz = (np.arange(corr.shape[a]) - (shape[a] - 1) for a in range(3))
    allowed = ((np.hypot(sx[:, None, None], sy[None, :, None]) * cell_m <= max_shift_m)
               & (np.abs(sz[None, None, :]) * cell_m <= max_dz_m))
    corr = np.where(allowed, corr, -np.inf)
    i = np.unravel_index(int(np.argmax(corr)), corr.shape)
    shift = np.array([sx[i[0]], sy[i[1]], sz[i[2]]], np.float64) * cell_m
    return shift, float(corr[i] / max(b_occ.sum(), 1.0))


def _yaw(theta: float, centre: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    c, s = np.cos(theta), np.sin(theta)
    t[:2, :2] = [[c, -s], [s, c]]
    t[:3, 3] = centre - t[:3, :3] @ centre
    return t


def align_yaw_shift(moving: Structure, fixed: Structure, init: np.ndarray, radii_m: tuple[float, ...] = (
        0.06, 0.04, 0.03, 0.02, 0.02, 0.015, 0.015), iterations: int = 3) -> tuple[np.ndarray, float, float]:
    """Point-to-plane ICP of `moving` onto `fixed` from `init` [4, 4], over yaw (about the moving points' centre)
    and x, y, z only: (transform [4, 4], share of moving points paired within the last radius, their rms
    point-to-plane distance in m). Each radius in turn pairs each moved point with its nearest fixed point
    within it and takes `iterations` Gauss-Newton steps; a leaf that moved, a fruit's former place or a stretch
    only one date saw simply finds no partner."""
    from scipy.spatial import cKDTree

    tree = cKDTree(fixed.points)
    t = np.array(init, np.float64)
    for radius in radii_m:
        for _ in range(iterations):
            p = moving.points @ t[:3, :3].T + t[:3, 3]
            d, j = tree.query(p, distance_upper_bound=radius, workers=-1)
            ok = np.isfinite(d)
            if ok.sum() < 10:
                return t, 0.0, float("nan")
            p, q, n = p[ok], fixed.points[j[ok]], fixed.normals[j[ok]]
            c = p.mean(0)
            jac = np.column_stack([(p[:, 0] - c[0]) * n[:, 1] - (p[:, 1] - c[1]) * n[:, 0], n])   # d/d(yaw, t)
            res = np.einsum("ij,ij->i", p - q, n)
            step = np.linalg.lstsq(jac.T @ jac + 1e-6 * len(p) * np.eye(4), -jac.T @ res, rcond=None)[0]
            upd = _yaw(step[0], c)
            upd[:3, 3] += step[1:]
            t = upd @ t
    p = moving.points @ t[:3, :3].T + t[:3, 3]
    d, j = tree.query(p, distance_upper_bound=radii_m[-1], workers=-1)
    ok = np.isfinite(d)
    rms = float(np.sqrt(np.mean(np.einsum("ij,ij->i", p[ok] - fixed.points[j[ok]], fixed.normals[j[ok]]) ** 2))) \
        if ok.any() else float("nan")
    return t, float(ok.mean()), rms


MIN_PAIRED = 0.5
"""An anchor of the correction along the row counts when at least this share of its stretch's points ends within
the last pairing radius of the fixed structure (less: a stretch the earlier dates did not see, or a wrong fit)."""


def _paired(tree, pts: np.ndarray, radius: float) -> np.ndarray:
    return np.isfinite(tree.query(pts, distance_upper_bound=radius, workers=-1)[0])


def _offset(tree, fixed: Structure, sel: np.ndarray, start: np.ndarray, radii_m: tuple[float, ...],
            iterations: int) -> np.ndarray:
    """Translation of points `sel` onto `fixed` from `start`: point-to-plane least squares with shrinking
    pairing radii; a direction the points hardly constrain is damped towards `start`."""
    off = start.copy()
    for radius in radii_m:
        for _ in range(iterations):
            d, j = tree.query(sel + off, distance_upper_bound=radius, workers=-1)
            ok = np.isfinite(d)
            if ok.sum() < 10:
                return off
            n = fixed.normals[j[ok]]
            res = np.einsum("ij,ij->i", sel[ok] + off - fixed.points[j[ok]], n)
            damp = 1e-3 * ok.sum()
            off = off + np.linalg.solve(n.T @ n + damp * np.eye(3), -n.T @ res - damp * (off - start))
    return off


def local_offsets(moving: np.ndarray, fixed: Structure, half_length_m: float,
                  radii_m: tuple[float, ...] = (0.05, 0.04, 0.03, 0.02, 0.02), iterations: int = 3,
                  min_points: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """(anchor x [P], offsets [P, 3]): along the row, every half_length_m, the translation that aligns the
    moving points [M, 3] within half_length_m of the anchor's x (already registered rigidly) onto `fixed`.
    Drift changes slowly along the row, so the anchors are fitted outward from the stretch the rigid part
    already fits best, each starting from its fitted neighbour's offset; an anchor whose stretch ends with
    under MIN_PAIRED of its points paired is left out."""
    from scipy.spatial import cKDTree

    tree = cKDTree(fixed.points)
    x0, x1 = float(moving[:, 0].min()), float(moving[:, 0].max())
    anchors = [(xa, sel) for xa in np.arange(x0, x1 + half_length_m, half_length_m)
               if len(sel := moving[np.abs(moving[:, 0] - xa) <= half_length_m]) >= min_points]
    if not anchors:
        return np.zeros(0), np.zeros((0, 3))
    fit0 = [_paired(tree, sel, radii_m[-1]).mean() for _, sel in anchors]
    best = int(np.argmax(fit0))
    found: dict[int, np.ndarray] = {}
    for order in (range(best, len(anchors)), range(best - 1, -1, -1)):
        start = found.get(best, np.zeros(3))
        for i in order:
            off = _offset(tree, fixed, anchors[i][1], start, radii_m, iterations)
            if _paired(tree, anchors[i][1] + off, radii_m[-1]).mean() >= MIN_PAIRED:
                found[i] = start = off
    keep = sorted(found)
    return (np.array([anchors[i][0] for i in keep], np.float64),
            np.array([found[i] for i in keep], np.float64).reshape(-1, 3))
