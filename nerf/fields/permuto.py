"""The radiance field: colour grid G_c -> density decoder -> colour decoder (view-dependent).

    h = D(G_c(x))            16 outputs, 1 hidden layer of `hidden` (ReLU)
    sigma = exp(min(h_0, 15))  (finite; an exponential with a clamped input, in float32: under float16
                                autocast exp(15) = 3.3e6 would overflow to inf)
    rgb = sigmoid(C([h, SH(d)]))  spherical harmonics of degree 2 for the view direction d
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from nerf.config import NerfConfig
from nerf.encoding import PermutoEncoding
from nerf.fields.base import MAX_LOG_DENSITY, ColourWhere, decode_colour, mlp


def sh_deg2(d: Tensor) -> Tensor:
    """Real spherical harmonics up to degree 2 of unit directions [N, 3] -> [N, 9]."""
    x, y, z = d.unbind(-1)
    return torch.stack([
        torch.full_like(x, 0.28209479), 0.48860251 * y, 0.48860251 * z, 0.48860251 * x,
        1.09254843 * x * y, 1.09254843 * y * z, 0.31539157 * (3 * z * z - 1), 1.09254843 * x * z,
        0.54627421 * (x * x - y * y)], -1)


class RadianceField(nn.Module):
    def __init__(self, cfg: NerfConfig, scene_scale_m: float):
        """`scene_scale_m`: metres per normalised unit (lattice scales are given in metres)."""
        super().__init__()
        self.grid = PermutoEncoding(n_levels=cfg.n_levels, n_features=cfg.n_features, log2_capacity=cfg.log2_capacity,
                                    coarsest_scale=cfg.coarsest_res_m / scene_scale_m,
                                    finest_scale=cfg.finest_res_m / scene_scale_m, seed=cfg.seed)
        self.density_net = mlp(self.grid.out_dim, cfg.hidden, 1, 16)
        self.color_net = mlp(16 + 9, cfg.hidden, 1, 3)

    @property
    def feature_dim(self) -> int:
        """Width of the features g_c that forward() returns (what the panoptic heads read)."""
        return self.grid.out_dim

    def param_groups(self, cfg: NerfConfig) -> list[dict]:
        """Adam parameter groups: the hash table (eps 1e-15: most rows see no gradient in a step) and the decoders."""
        return [{"params": [self.grid.table], "lr": cfg.lr_grid, "eps": 1e-15},
                {"params": list(self.density_net.parameters()) + list(self.color_net.parameters()), "lr": cfg.lr_mlp,
                 "weight_decay": 1e-6}]

    def feature_parameters(self) -> list[nn.Parameter]:
        """The parameters behind g_c (a 'shared' panoptic phase trains them too)."""
        return [self.grid.table]

    def density(self, x: Tensor, grid_features: Tensor | None = None) -> Tensor:
        """x [N, 3] -> sigma [N]; grid_features: self.grid(x) where already computed."""
        h = self.density_net(self.grid(x) if grid_features is None else grid_features)
        return torch.exp(h[:, 0].float().clamp(max=MAX_LOG_DENSITY))

    def forward(self, x: Tensor, d: Tensor | None, colour_where: ColourWhere | None = None,
                grid_features: Tensor | None = None) -> tuple[Tensor, Tensor | None, Tensor]:
        """x [N, 3] normalised positions, d [N, 3] unit directions -> sigma [N], rgb [N, 3], g_c [N, L*F]
        (d None: rgb None; colour_where: see decode_colour; grid_features: self.grid(x) from a no-grad call, given
        back with gradients by the grid, PermutoEncoding.forward's `known`)."""
        g = self.grid(x, known=grid_features)
        h = self.density_net(g)
        sigma = torch.exp(h[:, 0].float().clamp(max=MAX_LOG_DENSITY))
        rgb = None if d is None else decode_colour(self.color_net, h, d, sh_deg2, sigma, colour_where)
        return sigma, rgb, g
