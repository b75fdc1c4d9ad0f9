"""Per-frame pose corrections: continuous 6D rotation (Zhou et al. 2019) and a translation residual.

    R = [b1 b2 b3],  b1 = a1 / max(|a1|, eps),  b2 = normalise(a2 - (b1 . a2) b1),  b3 = b1 x b2
    c2w = c2w_init @ [R | t * scale_m]     (the correction acts in the camera frame)
Parameters start at a1 = e_x, a2 = e_y, t = 0 (identity). Every input gives a finite rotation (orthonormal,
det +1): each column is scaled by its largest entry before the norm (no overflow at 1e30, no underflow at
1e-30), a1 ~ 0 (or non-finite) falls back to e_x, and a2 ~ parallel to a1 falls back to the axis least
aligned with b1, made orthogonal to it. Gradients there are those of the fallback (zero), never NaN.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

EPS = 1e-8


def _unit(v: Tensor, fallback: Tensor) -> Tensor:
    """Rows of v [N, 3] scaled to unit length, `fallback` [N, 3] (unit) where v is ~0 or not finite."""
    v = torch.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0)
    big = v.abs().amax(-1, keepdim=True)
    ok = big > torch.finfo(v.dtype).tiny
    v = v / torch.where(ok, big, torch.ones_like(big))        # largest entry +-1: the norm is safe
    n = v.norm(dim=-1, keepdim=True)
    ok = ok & (n > EPS)
    return torch.where(ok, v / torch.where(ok, n, torch.ones_like(n)), fallback)


def rotation_6d(a: Tensor) -> Tensor:
    """[N, 6] -> [N, 3, 3] rotation matrices by Gram-Schmidt, finite and orthonormal for any input."""
    a1, a2 = a[:, :3], a[:, 3:]
    eye = torch.eye(3, dtype=a.dtype, device=a.device)
    b1 = _unit(a1, eye[0].expand_as(a1))
    # a2 scaled first, so that the projection is computed on numbers of order 1
    a2 = torch.nan_to_num(a2, nan=0.0, posinf=0.0, neginf=0.0)
    a2 = a2 / a2.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(a.dtype).tiny)
    # fallback for a2 ~ parallel to b1: the axis least aligned with b1, projected off it
    axis = eye[b1.abs().argmin(-1)]
    alt = axis - (b1 * axis).sum(-1, keepdim=True) * b1
    alt = alt / alt.norm(dim=-1, keepdim=True)
    # a residual below sqrt(machine eps) of |a2| ~ 1 is rounding noise: a2 is parallel to b1
    r = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    n = r.norm(dim=-1, keepdim=True)
    ok = n > torch.finfo(a.dtype).eps ** 0.5
    b2 = torch.where(ok, r / torch.where(ok, n, torch.ones_like(n)), alt)
    b2 = b2 - (b1 * b2).sum(-1, keepdim=True) * b1  # second pass: orthogonal to rounding precision
    b2 = b2 / b2.norm(dim=-1, keepdim=True)
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
        out[:, :3, 3] = self.shift_m(idx)
        return out

    def shift_m(self, idx: Tensor) -> Tensor:
        """[K] frame indices -> [K, 3] translation corrections in metres (camera frame; the norm is how far each
        camera centre moved from its initial pose)."""
        return self.trans[idx] * self.scale_m

    def apply(self, c2w_init: Tensor, idx: Tensor) -> Tensor:
        return c2w_init[idx] @ self.delta(idx)
