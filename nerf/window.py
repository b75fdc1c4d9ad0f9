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
