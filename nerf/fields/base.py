"""What every radiance field offers the renderer, the trainer and the panoptic heads (the `Field`
protocol), and the pieces fields are built from."""
from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

from torch import Tensor, nn

if TYPE_CHECKING:
    from nerf.config import NerfConfig
    from nerf.encoding import PermutoEncoding

MAX_LOG_DENSITY = 15.0
"""density = exp(min(h, MAX_LOG_DENSITY)): finite, and exp(15) = 3.3e6 stays inside float16 only as float32,
so the exponential is always taken in float32."""


@runtime_checkable
class Field(Protocol):
    """A radiance field: positions normalised to about [-1, 1] (nerf/window.py Scene) -> density, colour and
    the features the panoptic heads read."""

    grid: PermutoEncoding | None
    """the colour hash grid whose lattice a panoptic delta grid copies, or None for a field without one
    (only panoptic grid_mode 'shared' fits it)."""

    @property
    def feature_dim(self) -> int:
        """width of the features forward() returns."""
        ...

    def param_groups(self, cfg: NerfConfig) -> list[dict]:
        """Adam parameter groups of the field's parameters."""
        ...

    def feature_parameters(self) -> list[nn.Parameter]:
        """the parameters behind the features (a 'shared' panoptic phase trains them too)."""
        ...

    def density(self, x: Tensor) -> Tensor:
        """x [N, 3] -> sigma [N] (float32, >= 0, finite)."""
        ...

    def __call__(self, x: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """x [N, 3], unit directions d [N, 3] -> sigma [N], rgb [N, 3] in [0, 1], features [N, feature_dim]."""
        ...


def mlp(n_in: int, hidden: int, n_hidden: int, n_out: int) -> nn.Sequential:
    """n_hidden ReLU layers of width `hidden`, then a linear layer to n_out."""
    layers: list[nn.Module] = []
    d = n_in
    for _ in range(n_hidden):
        layers += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    layers.append(nn.Linear(d, n_out))
    return nn.Sequential(*layers)


def param_count(module: nn.Module) -> int:
    """Trainable parameters of a module."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
