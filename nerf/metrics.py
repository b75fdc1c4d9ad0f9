"""Image and trajectory metrics: PSNR, absolute trajectory error after alignment, rotation error."""
from __future__ import annotations

import math

import numpy as np
import torch

from nerf.geometry import align_similarity


def psnr_from_mse(mse: float) -> float:
    """PSNR (dB) of images in [0, 1] with mean squared error `mse`: -10 log10(mse), inf for 0.
    Example: mse 0.01 -> 20 dB."""
    return float("inf") if mse == 0 else -10 * math.log10(mse)


def psnr(pred: np.ndarray | torch.Tensor, target: np.ndarray | torch.Tensor) -> float:
    """PSNR (dB) of two images in [0, 1] (numpy arrays or torch tensors on any device, same shape),
    computed in float64."""
    as64 = lambda a: (a.detach().cpu().double().numpy() if isinstance(a, torch.Tensor)  # noqa: E731
                      else np.asarray(a, np.float64))
    return psnr_from_mse(float(np.mean((as64(pred) - as64(target)) ** 2)))


def ate_rmse(est: np.ndarray, gt: np.ndarray, align: str = "se3") -> float:
    """RMSE of positions [N, 3] after the best rigid ('se3') or similarity ('sim3') alignment, metres."""
    est, gt = np.asarray(est, np.float64), np.asarray(gt, np.float64)
    if len(est) < 3:
        return float(np.sqrt(np.mean(np.sum((est - gt) ** 2, 1))))
    s, r, t = align_similarity(est, gt, with_scale=align == "sim3")
    err = gt - (s * est @ r.T + t)
    return float(np.sqrt(np.mean(np.sum(err ** 2, 1))))


def rotation_error_deg(est: np.ndarray, gt: np.ndarray) -> float:
    """Mean geodesic angle between rotations [N, 3, 3] after removing the best common rotation."""
    est, gt = np.asarray(est, np.float64), np.asarray(gt, np.float64)
    _, r, _ = align_similarity(np.zeros((len(est), 3)), np.zeros((len(est), 3)), est, gt, with_scale=False,
                               position_weight=0.0, orientation_weight=1.0)   # chordal mean of R_gt R_est^T
    rel = np.einsum("ij,njk->nik", r, est)
    c = np.clip((np.trace(np.einsum("nji,njk->nik", rel, gt), axis1=1, axis2=2) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(c)).mean())
