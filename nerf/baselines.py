"""Baselines trained in the same harness as ours (trainer.fit_window, panoptic_fit.fit_panoptic), on the same
windows, for `pag bench compare`.

Semantic-NeRF-like (Zhi et al., 2021), scaled to a 2-core CPU: an MLP radiance field on a Fourier
(positional) encoding of the position and of the view direction, no hash grid, no occupancy-aware
capacity; a semantic head on the trunk's features and NO instance output. Select it with
`NerfConfig(field_kind="mlp_pe")` and train its semantic head with `SEMANTIC_ONLY`:

    gamma(p) = [p, sin(2^k pi p), cos(2^k pi p)]_{k < K}        K = POS_FREQS for x, DIR_FREQS for d
    h = trunk(gamma(x))                                          TRUNK_LAYERS x TRUNK_WIDTH, ReLU
    sigma = exp(min(w_sigma . h, 15)),  rgb = sigmoid(C([h, gamma(d)]))

Differences from the paper, all for CPU time: a trunk of 4 x 128 instead of 8 x 256, no hierarchical
sampling (it uses our occupancy-grid marching like every model in the comparison), and the semantic
head is trained after the colour phase on the shared trunk (PanopticConfig grid_mode='shared', so the
semantic loss reaches the trunk) instead of jointly from step 0.

Panoptic-Lifting-like needs no code: our permutohedral field with fixed poses (refine_poses=False), one
grid for colour and panoptic (grid_mode='shared') and plain linear assignment (id_window=False); see
PANOPTIC_LIFTING_LIKE.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from nerf.config import NerfConfig
from nerf.field import MAX_LOG_DENSITY, mlp
from nerf.panoptic import PanopticField
from nerf.panoptic_fit import PanopticConfig

POS_FREQS = 10
"""frequencies of the position encoding (Semantic-NeRF / NeRF: 10)."""
DIR_FREQS = 4
"""frequencies of the direction encoding (NeRF: 4)."""
TRUNK_LAYERS = 4
"""hidden layers of the trunk (NeRF: 8)."""
TRUNK_WIDTH = 128
"""width of the trunk (NeRF: 256)."""

OURS_OFF = dict(memory_prior=0.0, stuff_confidence=1.0, complete_3d=False, slot_reach_m=0.0, region_reach_m=0.0)
"""this project's additions to the panoptic phase, off for the baselines: the slot memory, the 3D instance
completion, the render-time slot and region reach and the lower weight of stuff labels (a pixel without detection)."""
SEMANTIC_ONLY = dict(grid_mode="shared", instances=False, id_window=False, **OURS_OFF)
"""PanopticConfig changes of the Semantic-NeRF-like baseline: semantic head on the trunk, no instances."""
PANOPTIC_LIFTING_LIKE = dict(grid_mode="shared", id_window=False, **OURS_OFF)
"""PanopticConfig changes of the Panoptic-Lifting-like baseline (plus NerfConfig refine_poses=False)."""


def fourier(x: Tensor, n_freqs: int) -> Tensor:
    """gamma(x) = [x, sin(2^k pi x), cos(2^k pi x)] for k < n_freqs: [N, D] -> [N, D (1 + 2 n_freqs)].
    Example: x = 0.5, n_freqs = 1 -> [0.5, sin(pi/2), cos(pi/2)] = [0.5, 1, 0]."""
    freqs = (2.0 ** torch.arange(n_freqs, device=x.device, dtype=torch.float32)) * math.pi  # [K]
    xb = x.float()[..., None] * freqs                                                       # [N, D, K]
    return torch.cat([x.float(), torch.sin(xb).flatten(1), torch.cos(xb).flatten(1)], -1)


class MlpPeField(nn.Module):
    """The Semantic-NeRF-like radiance field, with RadianceField's interface (density, forward -> sigma,
    rgb, features; param_groups, feature_parameters, feature_dim), so trainer.fit_window trains it as is."""

    def __init__(self, cfg: NerfConfig, scene_scale_m: float):
        super().__init__()
        del scene_scale_m  # positions arrive normalised to about [-1, 1]; the encoding needs no metres
        self.trunk = nn.Sequential(*mlp(3 * (1 + 2 * POS_FREQS), TRUNK_WIDTH, TRUNK_LAYERS - 1, TRUNK_WIDTH),
                                   nn.ReLU(inplace=True))
        self.sigma_out = nn.Linear(TRUNK_WIDTH, 1)
        self.color_net = mlp(TRUNK_WIDTH + 3 * (1 + 2 * DIR_FREQS), cfg.hidden, 1, 3)

    @property
    def feature_dim(self) -> int:
        return TRUNK_WIDTH

    def param_groups(self, cfg: NerfConfig) -> list[dict]:
        """One group: every weight is an MLP weight (learning rate lr_mlp)."""
        return [{"params": list(self.parameters()), "lr": cfg.lr_mlp, "weight_decay": 1e-6}]

    def feature_parameters(self) -> list[nn.Parameter]:
        """The trunk: what the semantic loss trains in a 'shared' panoptic phase."""
        return list(self.trunk.parameters())

    def features(self, x: Tensor) -> Tensor:
        return self.trunk(fourier(x, POS_FREQS))

    def density(self, x: Tensor) -> Tensor:
        return torch.exp(self.sigma_out(self.features(x))[:, 0].float().clamp(max=MAX_LOG_DENSITY))

    def forward(self, x: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """x [N, 3] normalised positions, d [N, 3] unit directions -> sigma [N], rgb [N, 3], trunk features [N, W]."""
        h = self.features(x)
        sigma = torch.exp(self.sigma_out(h)[:, 0].float().clamp(max=MAX_LOG_DENSITY))
        rgb = torch.sigmoid(self.color_net(torch.cat([h, fourier(d, DIR_FREQS)], -1)))
        return sigma, rgb, h

    def panoptic_field(self, cfg: PanopticConfig, n_slots: int, hidden: int) -> PanopticField:
        """The heads on the trunk's features (only grid_mode 'shared' makes sense: there is no grid to add a
        delta to)."""
        if cfg.grid_mode != "shared":
            raise ValueError(f"the mlp_pe field has no hash grid: panoptic grid_mode must be 'shared', got "
                             f"{cfg.grid_mode!r}")
        return PanopticField(1, TRUNK_WIDTH, 1, 1.0, 1.0, cfg.n_classes, n_slots, mode="shared", hidden=hidden)
