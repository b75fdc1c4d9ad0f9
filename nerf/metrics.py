"""Image and trajectory metrics: PSNR, absolute trajectory error after alignment, rotation error."""
from __future__ import annotations

import math

import numpy as np


def psnr(pred: np.ndarray, target: np.ndarray) -> float:
    """Images in [0, 1]; dB."""
    mse = float(np.mean((np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10 * math.log10(mse)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """R, t, s minimising |dst - (s R src + t)|^2 (Umeyama 1991). src, dst [N, 3]."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    sgn = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sgn[2, 2] = -1
    r = u @ sgn @ vt
    var = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(d) @ sgn) / var) if with_scale and var > 0 else 1.0
    return r, mu_d - s * r @ mu_s, s


def ate_rmse(est: np.ndarray, gt: np.ndarray, align: str = "se3") -> float:
    """RMSE of positions [N, 3] after the best rigid ('se3') or similarity ('sim3') alignment, metres."""
    est, gt = np.asarray(est, np.float64), np.asarray(gt, np.float64)
    if len(est) < 3:
        return float(np.sqrt(np.mean(np.sum((est - gt) ** 2, 1))))
    r, t, s = umeyama(est, gt, align == "sim3")
    err = gt - (s * est @ r.T + t)
    return float(np.sqrt(np.mean(np.sum(err ** 2, 1))))


def rotation_error_deg(est: np.ndarray, gt: np.ndarray) -> float:
    """Mean geodesic angle between rotations [N, 3, 3] after removing the best common rotation."""
    est, gt = np.asarray(est, np.float64), np.asarray(gt, np.float64)
    m = np.einsum("nij,nkj->ik", gt, est)          # sum_n R_gt R_est^T
    u, _, vt = np.linalg.svd(m)
    r = u @ np.diag([1, 1, np.sign(np.linalg.det(u @ vt))]) @ vt
    rel = np.einsum("ij,njk->nik", r, est)
    c = np.clip((np.trace(np.einsum("nji,njk->nik", rel, gt), axis1=1, axis2=2) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(c)).mean())
