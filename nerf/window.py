"""A window's input to a fit (WindowData: images, depths, intrinsics, initial poses, split) and its
normalisation into the field's coordinates (Scene)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


@dataclass
class WindowData:
    images: np.ndarray
    """[N, H, W, 3] uint8 RGB."""
    depths: np.ndarray
    """[N, H, W] float32 metres, 0 = invalid."""
    intrinsics: np.ndarray
    """[N, 4] fx, fy, cx, cy."""
    poses_c2w: np.ndarray
    """[N, 4, 4] initial camera-to-world poses (OpenCV camera)."""
    is_train: np.ndarray
    """[N] bool."""
    frame_ids: np.ndarray
    """[N] frame ids (for messages)."""

    def __post_init__(self) -> None:
        n = len(self.images)
        for name in ("depths", "intrinsics", "poses_c2w", "is_train", "frame_ids"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"WindowData.{name} has {len(getattr(self, name))} entries, images have {n}")
        if not self.is_train.any():
            raise ValueError("a window needs at least one training frame")
        if not np.isfinite(self.poses_c2w).all():
            raise ValueError("a window's initial poses contain non-finite values")

    def take(self, idx: np.ndarray) -> "WindowData":
        """The window with only the frames `idx` (indices into its frames), in that order."""
        return WindowData(self.images[idx], self.depths[idx], self.intrinsics[idx], self.poses_c2w[idx],
                          self.is_train[idx], self.frame_ids[idx])


@dataclass
class Scene:
    """Normalisation of the window: field input = (x - centre) / scale_m; bounds in metres."""

    centre: Tensor
    scale_m: float
    lo: Tensor
    hi: Tensor

    def normalise(self, x: Tensor) -> Tensor:
        return (x - self.centre) / self.scale_m

    def to(self, device) -> "Scene":
        return Scene(self.centre.to(device), self.scale_m, self.lo.to(device), self.hi.to(device))


FAR_PERCENTILE = 99.0
"""The far plane covers this percentile of a window's valid sensor depth (the rest: flying pixels, glare)."""
FAR_MARGIN = 1.1
"""... times this margin (depth noise and surfaces just past the percentile)."""
RANGE_QUANTUM_M = 0.5
"""Derived depth limits are rounded up to a multiple of this (metres), so the windows of one recording get
the same limit from slightly different depth samples."""
FALLBACK_FAR_M = 3.5
"""Far plane (metres) of a window without any valid depth: a glasshouse row with its far row and wall."""


def valid_depth_sample(depths: np.ndarray, max_values: int = 1 << 21) -> np.ndarray:
    """The valid (finite, > 0) values of depth images [N, H, W] (metres), from an even subsample of at most
    about `max_values` pixels."""
    flat = np.asarray(depths).reshape(-1)
    step = max(1, flat.size // max_values)
    v = flat[::step]
    return v[np.isfinite(v) & (v > 0)]


def round_up(x_m: float, quantum_m: float = RANGE_QUANTUM_M) -> float:
    """x_m rounded up to a multiple of quantum_m. Example: 3.34 -> 3.5, 6.52 -> 7.0."""
    return float(np.ceil(x_m / quantum_m - 1e-9) * quantum_m)


def depth_far_m(depths: np.ndarray) -> float:
    """The far plane of a window from its sensor depth [N, H, W] (metres, 0 = none): FAR_MARGIN x the
    FAR_PERCENTILE of the valid depth, rounded up to RANGE_QUANTUM_M (FALLBACK_FAR_M without valid depth).
    Example: a glasshouse row whose wall is at 3 m (99th percentile 3.04 m) -> 3.5 m; an office whose
    99th percentile is 5.93 m -> 7.0 m."""
    v = valid_depth_sample(depths)
    if v.size == 0:
        return FALLBACK_FAR_M
    return round_up(FAR_MARGIN * float(np.percentile(v, FAR_PERCENTILE)))


PARALLAX_PERCENTILES = (10.0, 90.0)
"""The parallax spread of a window: the range of inverse valid depth between these percentiles (1/m)."""
MIN_PARALLAX_PER_M = 0.01
"""Floor of the parallax spread (1/m): a window that sees one flat wall at one depth has none."""


def parallax_spread(depths: np.ndarray) -> float:
    """How differently a sideways camera shift moves a window's near and far surfaces in its images: the
    PARALLAX_PERCENTILES range of 1 / depth over the valid depth of [N, H, W] (metres, 0 = none), in 1/m,
    floored at MIN_PARALLAX_PER_M; NaN without valid depth. A shift t (m) moves a surface at depth z by
    t / z radians; a turn moves every surface alike, so colour tells a shift from a turn only by this
    difference. Example: a glasshouse row (plants at 0.5-0.6 m, far row at 2-3 m) 1.5; an office (walls
    at 1.8-3.6 m) 0.28."""
    v = valid_depth_sample(depths)
    if v.size == 0:
        return float("nan")
    lo, hi = np.percentile(1.0 / v, PARALLAX_PERCENTILES)
    return max(float(hi - lo), MIN_PARALLAX_PER_M)


def window_scene(poses: np.ndarray, k: np.ndarray, wh: tuple[int, int], far_m: float) -> Scene:
    """Bounds = the box around every camera centre and its frustum corners at `far_m`."""
    w, h = wh
    pts = [poses[:, :3, 3]]
    for u, v in ((0, 0), (w, 0), (0, h), (w, h)):
        d = np.stack([(u - k[:, 2]) / k[:, 0], (v - k[:, 3]) / k[:, 1], np.ones(len(k))], -1)
        pts.append(poses[:, :3, 3] + np.einsum("nij,nj->ni", poses[:, :3, :3], d) * far_m)
    pts = np.concatenate(pts)
    lo, hi = pts.min(0) - 0.05, pts.max(0) + 0.05
    centre = (lo + hi) / 2
    scale = float((hi - lo).max() / 2)
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return Scene(t(centre), scale, t(lo), t(hi))
