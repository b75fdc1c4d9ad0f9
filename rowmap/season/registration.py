"""Register one date's row frame onto the season frame (the first date's): on the rows' static structure
(`register_structure`, rowmap/structure.py) where both sides have one, else on the fruits both dates show.

Odometry origins differ between dates (the robot starts elsewhere) and fruits grow, are picked and set, so
on the fruits the transform is found by consensus (`register`): every pairing of a moving fruit with a fixed
fruit of a compatible size and height proposes a translation; the one most other fruits agree with (within
`seed_inlier_m`) wins, and a few rounds of least squares over mutual nearest neighbours, with a shrinking inlier radius,
refine x, y, z and yaw (the row frames are gravity-aligned: roll and pitch are not estimated).

Each date's row frame drifts along the row with its own odometry (a few cm per metre), so no single rigid
transform fits a whole row to within a centimetre. On top of the rigid transform a smooth correction along
the row takes up the rest: at a point with row coordinate x, c(x) = a from a local linear fit of the anchors'
residuals r_i at x_i (the paired fruits; with the structure, also each stretch's own alignment),

    min_{a, b} sum_i w_i |r_i - a - b (x_i - x)|^2 + PRIOR_WEIGHT (|a|^2 + h^2 |b|^2),
    w_i = exp(-(x_i - x)^2 / (2 h^2)),  h = max(bandwidth_m, distance to the MIN_NEIGHBOURS-th nearest x_i),

so odometry drift that grows along the row is followed, continued past the last pairs, and shrunk towards
the rigid transform where pairs are few.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rowmap import structure as st

GROW_ROUNDS = 4
"""Rounds of pairing at the seed radius, each with the correction of the round before."""
PRIOR_WEIGHT = 0.1
"""Weight (in pairs) of the rigid transform in the correction along the row: one lone pair moves its
neighbourhood by 10/11 of its residual."""
MIN_NEIGHBOURS = 4
"""The correction at any point is fitted to at least this many pairs (the bandwidth widens to reach them)."""


@dataclass(frozen=True)
class Registration:
    transform: np.ndarray
    """[4, 4] rigid part: moving row frame -> season frame."""
    inliers: int
    """fruit pairs the final registration agrees on."""
    rms_m: float
    """root mean square distance of those pairs after registration."""
    anchors_x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """[P] row coordinate x (after the rigid part) of the pairs the correction is built from."""
    residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """[P, 3] their residuals after the rigid part."""
    bandwidth_m: float = 0.3

    def __call__(self, xyz: np.ndarray) -> np.ndarray:
        """[N, 3] row-frame points -> season frame (rigid part, then the correction along the row)."""
        p = apply(self.transform, xyz)
        return p + correction(p[:, 0], self.anchors_x, self.residuals, self.bandwidth_m)


IDENTITY = Registration(np.eye(4), 0, float("nan"))


def apply(transform: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """[N, 3] points through a [4, 4] transform."""
    return np.asarray(xyz, np.float64).reshape(-1, 3) @ transform[:3, :3].T + transform[:3, 3]


def correction(x: np.ndarray, anchors_x: np.ndarray, residuals: np.ndarray, bandwidth_m: float) -> np.ndarray:
    """[N, 3] smooth correction at row coordinates x [N]: a local linear fit (module docstring) of the anchors'
    residuals [P, 3] around each x, Gaussian weights over max(bandwidth_m, the distance to the MIN_NEIGHBOURS-th
    nearest anchor), so beyond the last anchors it continues their trend. Example: anchors at x = 0 and 1 m with
    residuals 0 and 0.02 m (bandwidth 0.3 m) give 0.0092 m at x = 0.5 m and 0.0194 m at x = 1.5 m (the prior
    holds the two-point slope back a little)."""
    x = np.asarray(x, np.float64)
    if len(anchors_x) == 0:
        return np.zeros((len(x), 3))
    d = anchors_x[None] - x[:, None]                                                     # [N, P]
    k = min(len(anchors_x), MIN_NEIGHBOURS)
    bw = np.maximum(bandwidth_m, np.sort(np.abs(d), axis=1)[:, k - 1])[:, None]          # [N, 1]
    w = np.exp(-0.5 * (d / bw) ** 2)
    s0 = w.sum(1) + PRIOR_WEIGHT
    s1 = (w * d).sum(1)
    s2 = (w * d * d).sum(1) + PRIOR_WEIGHT * bw[:, 0] ** 2
    t0, t1 = w @ residuals, (w * d) @ residuals                                         # [N, 3]
    return (s2[:, None] * t0 - s1[:, None] * t1) / (s0 * s2 - s1 * s1)[:, None]


def fit_yaw_translation(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rotation about z plus translation taking src [N, 3] onto dst [N, 3] (N >= 1; yaw 0 for N = 1).
    Closed form: yaw = atan2(sum(a x b)_z, sum(a . b)_xy) of the centred xy coordinates."""
    cs, cd = src.mean(0), dst.mean(0)
    a, b = src[:, :2] - cs[:2], dst[:, :2] - cd[:2]
    yaw = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b)) if len(src) > 1 else 0.0
    t = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    t[:2, :2] = [[c, -s], [s, c]]
    t[:3, 3] = cd - t[:3, :3] @ cs
    return t


def _mutual_nearest(a: np.ndarray, b: np.ndarray, max_m: float) -> tuple[np.ndarray, np.ndarray]:
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    i = np.arange(len(a))
    j = d.argmin(1)
    ok = (d.argmin(0)[j] == i) & (d[i, j] <= max_m)
    return i[ok], j[ok]


def register(moving: np.ndarray, fixed: np.ndarray, moving_d: np.ndarray, fixed_d: np.ndarray,
             max_shift_m: float, seed_inlier_m: float = 0.05, final_inlier_m: float = 0.02,
             size_tolerance_m: float = 0.03, bandwidth_m: float = 0.3) -> Registration:
    """Transform [4, 4] that takes `moving` fruit centres [M, 3] (diameters moving_d [M]) onto `fixed` [F, 3]
    (fixed_d [F]). Candidate pairs: horizontal offset <= max_shift_m, height offset <= 3 x seed_inlier_m,
    |diameter difference| <= size_tolerance_m plus growth is not judged here (a fruit may have grown a
    few cm between dates: the tolerance is applied one way, to shrinking). Too few fruits: the identity."""
    moving, fixed = np.asarray(moving, np.float64), np.asarray(fixed, np.float64)
    if len(moving) == 0 or len(fixed) == 0:
        return IDENTITY
    off = fixed[None] - moving[:, None]                                          # [M, F, 3]
    ok = (np.linalg.norm(off[..., :2], axis=2) <= max_shift_m) & (np.abs(off[..., 2]) <= 3 * seed_inlier_m)
    md, fd = np.nan_to_num(np.asarray(moving_d, np.float64)), np.nan_to_num(np.asarray(fixed_d, np.float64))
    ok &= md[:, None] >= fd[None] - size_tolerance_m
    best, best_score = np.zeros(3), -1.0
    for shift in off[ok]:
        d = np.linalg.norm(moving[:, None] + shift - fixed[None], axis=2).min(1)
        score = float(np.sum(np.clip(1 - d / seed_inlier_m, 0, None)))           # soft inlier count
        if score > best_score:
            best, best_score = shift, score
    t = np.eye(4)
    t[:3, 3] = best
    reg = Registration(t, 0, float("nan"), bandwidth_m=bandwidth_m)
    # rounds at the seed radius first: the pairs found with the correction so far bring in their neighbours, which
    # the drift had kept apart; then the radius shrinks to the final one
    for radius in [seed_inlier_m] * GROW_ROUNDS + list(np.geomspace(seed_inlier_m, final_inlier_m, 4)):
        i, j = _mutual_nearest(reg(moving), fixed, radius)
        if len(i) == 0:
            break
        t = fit_yaw_translation(moving[i], fixed[j]) if len(i) >= 3 else fit_yaw_translation(
            moving[i].mean(0, keepdims=True), fixed[j].mean(0, keepdims=True))  # yaw needs a spread of pairs
        rigid = apply(t, moving[i])
        reg = Registration(t, 0, float("nan"), rigid[:, 0], fixed[j] - rigid, bandwidth_m)
    return agreement(reg, moving, fixed, final_inlier_m)


def agreement(reg: Registration, moving: np.ndarray, fixed: np.ndarray, inlier_m: float) -> Registration:
    """`reg` with its inliers and rms_m counted over the mutual nearest pairs of `moving` [M, 3] (through reg) and
    `fixed` [F, 3] within inlier_m."""
    if len(moving) == 0 or len(fixed) == 0:
        return Registration(reg.transform, 0, float("nan"), reg.anchors_x, reg.residuals, reg.bandwidth_m)
    i, j = _mutual_nearest(reg(moving), fixed, inlier_m)
    rms = float(np.sqrt(np.mean(np.sum((reg(moving[i]) - fixed[j]) ** 2, 1)))) if len(i) else float("nan")
    return Registration(reg.transform, int(len(i)), rms, reg.anchors_x, reg.residuals, reg.bandwidth_m)


def register_structure(moving: st.Structure, fixed: st.Structure, fruit_reg: Registration, max_shift_m: float,
                       bandwidth_m: float, fruits: tuple[np.ndarray, np.ndarray] | None = None,
                       inlier_m: float = 0.02) -> tuple[Registration, float]:
    """(registration of the `moving` date's structure onto the `fixed` structure of the dates before it, the
    share of its structure points that agree within the ICP's last radius). The rigid part is the ICP
    (rowmap/structure.py align_yaw_shift) that ends with the most agreeing points, started from the structure's
    own coarse shift and from the fruits' registration where their consensus found pairs. The correction along
    the row is fitted to each stretch's own alignment (local_offsets, every half bandwidth_m) together with
    the residuals of the fruit pairs `fruits` = (moving [M, 3], fixed [F, 3]) that agree within inlier_m."""
    shift, _ = st.coarse_shift(moving.points, fixed.points, max_shift_m)
    inits = [np.eye(4)]
    inits[0][:3, 3] = shift
    if fruit_reg.inliers >= 3:
        inits.append(fruit_reg.transform)
    t, share, _ = max((st.align_yaw_shift(moving, fixed, init) for init in inits), key=lambda r: r[1])
    xs, offsets = st.local_offsets(apply(t, moving.points), fixed, bandwidth_m / 2)
    reg = Registration(t, 0, float("nan"), xs, offsets, bandwidth_m)
    if fruits is not None and len(fruits[0]) and len(fruits[1]):
        i, j = _mutual_nearest(reg(fruits[0]), fruits[1], inlier_m)
        rigid = apply(t, fruits[0][i])
        reg = Registration(t, 0, float("nan"), np.concatenate([xs, rigid[:, 0]]),
                           np.concatenate([offsets, fruits[1][j] - rigid]), bandwidth_m)
    return reg, share
