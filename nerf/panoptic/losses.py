"""Panoptic losses on per-ray class / slot distributions (rows sum to 1), computed in log space.

    L_sem  = sum_r c_r * CE(p_sem(r), y_r) / sum_r c_r        c_r = detector confidence of the ray's segment
    L_inst = mean over thing rays of -log p_inst(r)[slot(segment(r))]  (slots from the per-frame assignment)
Rays whose confidence or weight is not finite (NaN, inf) are left out of the weighted losses.
    L_stuff = mean over stuff rays of -log p_inst(r)[0]
    L_cons = mean over thing rays of || p_inst(r) - mean_{r' in segment(r)} p_inst(r') ||^2   (weak)

Probabilities are clamped to >= EPS before the log, so no loss is ever inf or NaN.
"""
from __future__ import annotations

import torch
from torch import Tensor

EPS = 1e-6


def safe_log(p: Tensor) -> Tensor:
    return torch.log(p.clamp_min(EPS))


def semantic_loss(p_sem: Tensor, labels: Tensor, confidence: Tensor, void: int = 255) -> Tensor:
    """p_sem [R, D], labels [R] (void ignored), confidence [R] >= 0 -> scalar."""
    keep = (labels != void) & (labels >= 0) & (labels < p_sem.shape[1]) & torch.isfinite(confidence)
    if not keep.any():
        return p_sem.sum() * 0.0
    c = confidence[keep].clamp(0.0, 1.0)
    nll = -safe_log(p_sem[keep].gather(1, labels[keep].long()[:, None])[:, 0])
    return (c * nll).sum() / c.sum().clamp_min(EPS)


def instance_loss(p_inst: Tensor, target_slot: Tensor, weight: Tensor | None = None) -> Tensor:
    """p_inst [R, N], target_slot [R] (slot per ray, -1 = ignore), optional weight [R] >= 0 -> scalar
    (weighted) mean NLL. Rays with a non-finite weight are skipped, as in semantic_loss."""
    keep = target_slot >= 0
    if weight is not None:
        keep = keep & torch.isfinite(weight)
    if not keep.any():
        return p_inst.sum() * 0.0
    nll = -safe_log(p_inst[keep].gather(1, target_slot[keep].long()[:, None])[:, 0])
    if weight is None:
        return nll.mean()
    w = weight[keep].clamp_min(0.0)
    return (w * nll).sum() / w.sum().clamp_min(EPS)


def consistency_loss(p_inst: Tensor, seg_index: Tensor, n_segments: int) -> Tensor:
    """Pull the rays of a segment towards the segment's mean distribution. seg_index [R] (-1 = none)."""
    keep = seg_index >= 0
    if not keep.any() or n_segments == 0:
        return p_inst.sum() * 0.0
    p, s = p_inst[keep], seg_index[keep]
    sums = torch.zeros(n_segments, p.shape[1], dtype=p.dtype, device=p.device).index_add_(0, s, p)
    counts = torch.bincount(s, minlength=n_segments).clamp_min(1).to(p.dtype)
    mean = (sums / counts[:, None])[s].detach()
    return ((p - mean) ** 2).sum(-1).mean()
