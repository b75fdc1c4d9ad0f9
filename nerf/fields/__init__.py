"""Radiance fields behind one interface (base.Field): the permutohedral hash-grid field (ours) and the
MLP-on-Fourier-features baseline; `build_field` picks the one NerfConfig.field_kind names."""
from __future__ import annotations

from collections.abc import Callable

from torch import nn

from nerf.config import NerfConfig
from nerf.fields.base import MAX_LOG_DENSITY, Field, mlp, param_count
from nerf.fields.mlp_pe import MlpPeField
from nerf.fields.permuto import RadianceField

FIELD_KINDS: dict[str, Callable[[NerfConfig, float], nn.Module]] = {"permuto": RadianceField, "mlp_pe": MlpPeField}
"""field_kind -> constructor (cfg, metres per normalised unit)."""


def build_field(cfg: NerfConfig, scene_scale_m: float) -> nn.Module:
    """The radiance field cfg.field_kind names (FIELD_KINDS), for a scene of `scene_scale_m` metres per
    normalised unit."""
    if cfg.field_kind not in FIELD_KINDS:
        raise ValueError(f"unknown field_kind {cfg.field_kind!r}; field kinds: {sorted(FIELD_KINDS)}")
    return FIELD_KINDS[cfg.field_kind](cfg, scene_scale_m)


__all__ = ["FIELD_KINDS", "MAX_LOG_DENSITY", "Field", "MlpPeField", "RadianceField", "build_field", "mlp",
           "param_count"]
