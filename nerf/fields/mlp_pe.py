"""The Semantic-NeRF-like radiance field (Zhi et al., 2021), scaled to a 2-core CPU: an MLP on a Fourier
(positional) encoding of the position and of the view direction, no hash grid.

    gamma(p) = [p, sin(2^k pi p), cos(2^k pi p)]_{k < K}        K = POS_FREQS for x, DIR_FREQS for d
    h = trunk(gamma(x))                                          TRUNK_LAYERS x TRUNK_WIDTH, ReLU
    sigma = exp(min(w_sigma . h, 15)),  rgb = sigmoid(C([h, gamma(d)]))

Differences from the paper, all for CPU time: a trunk of 4 x 128 instead of 8 x 256, a colour head 64 wide
instead of 128 and no hierarchical sampling (it uses the occupancy-grid marching like every model). Its
semantic head reads the trunk's features (panoptic grid_mode 'shared'); nerf/baselines.py holds the
baseline's panoptic settings.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from nerf.config import NerfConfig
from nerf.fields.base import MAX_LOG_DENSITY, ColourWhere, decode_colour, mlp

POS_FREQS = 10
"""frequencies of the position encoding (Semantic-NeRF / NeRF: 10)."""
DIR_FREQS = 4
"""frequencies of the direction encoding (NeRF: 4)."""
TRUNK_LAYERS = 4
"""hidden layers of the trunk (NeRF: 8)."""
TRUNK_WIDTH = 128
"""width of the trunk (NeRF: 256)."""
COLOUR_WIDTH = 64
"""width of the colour head's hidden layer (NeRF: 128); the baseline's own, not NerfConfig.hidden, so the
baseline stays the same model whatever width a preset gives our decoders."""


def fourier(x: Tensor, n_freqs: int) -> Tensor:
    """gamma(x) = [x, sin(2^k pi x), cos(2^k pi x)] for k < n_freqs: [N, D] -> [N, D (1 + 2 n_freqs)].
    Example: x = 0.5, n_freqs = 1 -> [0.5, sin(pi/2), cos(pi/2)] = [0.5, 1, 0]."""
    freqs = (2.0 ** torch.arange(n_freqs, device=x.device, dtype=torch.float32)) * math.pi  # [K]
    xb = x.float()[..., None] * freqs                                                       # [N, D, K]
    return torch.cat([x.float(), torch.sin(xb).flatten(1), torch.cos(xb).flatten(1)], -1)


def _encode_dirs(d: Tensor) -> Tensor:
    return fourier(d, DIR_FREQS)


class MlpPeField(nn.Module):
    """The Semantic-NeRF-like radiance field (a `Field` without a hash grid)."""

    grid = None

    def __init__(self, cfg: NerfConfig, scene_scale_m: float):
        super().__init__()
        del scene_scale_m  # positions arrive normalised to about [-1, 1]; the encoding needs no metres
        self.trunk = nn.Sequential(*mlp(3 * (1 + 2 * POS_FREQS), TRUNK_WIDTH, TRUNK_LAYERS - 1, TRUNK_WIDTH),
                                   nn.ReLU(inplace=True))
        self.sigma_out = nn.Linear(TRUNK_WIDTH, 1)
        self.color_net = mlp(TRUNK_WIDTH + 3 * (1 + 2 * DIR_FREQS), COLOUR_WIDTH, 1, 3)

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

    def density(self, x: Tensor, grid_features: None = None) -> Tensor:
        if grid_features is not None:
            raise ValueError("the mlp_pe field has no hash grid: grid_features must be None")
        return torch.exp(self.sigma_out(self.features(x))[:, 0].float().clamp(max=MAX_LOG_DENSITY))

    def forward(self, x: Tensor, d: Tensor | None, colour_where: ColourWhere | None = None,
                grid_features: None = None) -> tuple[Tensor, Tensor | None, Tensor]:
        """x [N, 3] normalised positions, d [N, 3] unit directions -> sigma [N], rgb [N, 3], trunk features [N, W]
        (d None: rgb None; colour_where: see decode_colour; no grid, so no grid_features)."""
        if grid_features is not None:
            raise ValueError("the mlp_pe field has no hash grid: grid_features must be None")
        h = self.features(x)
        sigma = torch.exp(self.sigma_out(h)[:, 0].float().clamp(max=MAX_LOG_DENSITY))
        rgb = None if d is None else decode_colour(self.color_net, h, d, _encode_dirs, sigma, colour_where)
        return sigma, rgb, h
