"""Panoptic part of the field: the delta grid and the semantic / instance heads, and their integration.

    g_p(x) = stopgrad(g_c(x)) + delta_g_p(x)        (mode "delta", the PAg-NeRF design)
    g_p(x) = g_c(x)                                  (mode "shared": one grid, panoptic losses reach it)
    g_p(x) = G_p(x), an independent full-size grid   (mode "independent")

The semantic head (2 hidden layers of PanopticConfig.hidden units) gives logits over D classes, the instance
head (3 hidden layers) logits over N slots (slot 0 = stuff). Logits become probabilities per SAMPLE (softmax
before integration) and are integrated along each ray with the colour weights detached, so the
panoptic losses can move neither density nor camera poses.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from nerf.config import GridMode, PanopticConfig
from nerf.encoding import PermutoEncoding
from nerf.fields.base import mlp


class PanopticField(nn.Module):
    def __init__(self, n_levels: int, n_features: int, log2_capacity: int, coarsest_scale: float,
                 finest_scale: float, n_classes: int, n_slots: int, mode: GridMode = "delta",
                 hidden: int = PanopticConfig.hidden, seed: int = 1):
        super().__init__()
        if mode not in ("delta", "shared", "independent"):
            raise ValueError(f"panoptic grid mode must be delta, shared or independent, got {mode!r}")
        if n_slots < 2:
            raise ValueError(f"need at least 2 instance slots (slot 0 is stuff), got {n_slots}")
        self.mode = mode
        self.grid: PermutoEncoding | None = None
        if mode != "shared":
            # The delta starts at zero, so g_p starts as the colour features.
            self.grid = PermutoEncoding(n_levels=n_levels, n_features=n_features, log2_capacity=log2_capacity,
                                        coarsest_scale=coarsest_scale, finest_scale=finest_scale, seed=seed,
                                        init_std=0.0 if mode == "delta" else 1e-4)
        d = n_levels * n_features
        self.semantic = mlp(d, hidden, 2, n_classes)
        self.instance = mlp(d, hidden, 3, n_slots)

    def features(self, x: Tensor, g_c: Tensor) -> Tensor:
        """x [S, 3] normalised positions, g_c [S, L*F] colour-grid features -> g_p [S, L*F]."""
        if self.mode == "delta":
            return g_c.detach() + self.grid(x.detach())
        if self.mode == "shared":
            return g_c
        return self.grid(x.detach())

    def forward(self, x: Tensor, g_c: Tensor) -> tuple[Tensor, Tensor]:
        """-> semantic logits [S, D], instance logits [S, N] (float32, finite for finite inputs)."""
        g = self.features(x, g_c).float()
        return self.semantic(g), self.instance(g)


def integrate_probs(logits: Tensor, weights: Tensor, ray_index: Tensor, n_rays: int) -> Tensor:
    """Per-ray class distribution: sum_i stopgrad(w_i) * softmax(logits_i), renormalised by the ray's
    opacity (a ray that hits nothing gets the uniform distribution).

    logits [S, K], weights [S], ray_index [S] in 0..n_rays-1 -> [n_rays, K], rows sum to 1.
    Example: two samples with w = (0.5, 0.25), softmax rows (1, 0) and (0, 1) -> (2/3, 1/3).
    """
    probs = torch.softmax(logits.float(), dim=-1) * weights.detach().float()[:, None]
    k = logits.shape[-1]
    acc = torch.zeros(n_rays, k, dtype=probs.dtype, device=probs.device).index_add_(0, ray_index, probs)
    opacity = acc.sum(-1, keepdim=True)
    uniform = torch.full_like(acc, 1.0 / k)
    return torch.where(opacity > 1e-6, acc / opacity.clamp_min(1e-6), uniform)
