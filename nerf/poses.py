"""Per-frame pose corrections: continuous 6D rotation (Zhou et al. 2019) and a translation residual.

    R = [b1 b2 b3],  b1 = a1 / max(|a1|, eps),  b2 = normalise(a2 - (b1 . a2) b1),  b3 = b1 x b2
    c2w = c2w_init @ [R | t * scale_m]     (the correction acts in the camera frame)
Parameters start at a1 = e_x, a2 = e_y, t = 0 (identity). Degenerate 6D inputs (a1 = 0, a2 parallel
to a1) give a finite (possibly singular) matrix, never NaN.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

EPS = 1e-8


def rotation_6d(a: Tensor) -> Tensor:
    """[N, 6] -> [N, 3, 3] rotation matrices by Gram-Schmidt with an epsilon."""
    a1, a2 = a[:, :3], a[:, 3:]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(EPS)
    b2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = b2 / b2.norm(dim=-1, keepdim=True).clamp_min(EPS)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], -1)


class PoseCorrection(nn.Module):
    def __init__(self, n_frames: int, scale_m: float):
        super().__init__()
        init = torch.tensor([1.0, 0, 0, 0, 1.0, 0]).repeat(n_frames, 1)
        self.rot6d = nn.Parameter(init)
        self.trans = nn.Parameter(torch.zeros(n_frames, 3))
        self.scale_m = scale_m

    def delta(self, idx: Tensor) -> Tensor:
        """[K] frame indices -> [K, 4, 4] correction transforms."""
        out = torch.eye(4, device=self.trans.device).repeat(idx.shape[0], 1, 1)
        out[:, :3, :3] = rotation_6d(self.rot6d[idx])
        out[:, :3, 3] = self.trans[idx] * self.scale_m
        return out

    def apply(self, c2w_init: Tensor, idx: Tensor) -> Tensor:
        return c2w_init[idx] @ self.delta(idx)
