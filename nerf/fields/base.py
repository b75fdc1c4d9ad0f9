"""What every radiance field offers the renderer, the trainer and the panoptic heads (the `Field`
protocol), and the pieces fields are built from."""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Protocol, runtime_checkable

import torch
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

    def density(self, x: Tensor, grid_features: Tensor | None = None) -> Tensor:
        """x [N, 3] -> sigma [N] (float32, >= 0, finite); grid_features: grid(x) already computed (only a field
        with a grid)."""
        ...

    def __call__(self, x: Tensor, d: Tensor | None, colour_where: ColourWhere | None = None,
                 grid_features: Tensor | None = None) -> tuple[Tensor, Tensor | None, Tensor]:
        """x [N, 3], unit directions d [N, 3] -> sigma [N], rgb [N, 3] in [0, 1], features [N, feature_dim];
        d None: no colour (rgb None), for callers that need only density and features. colour_where: see
        decode_colour; grid_features: grid(x) already computed without gradients (only a field with a grid)."""
        ...


ColourWhere = Callable[[Tensor], Tensor]
"""sigma [N] -> bool [N]: the samples whose colour a caller needs (decode_colour)."""


def decode_colour(net: nn.Module, h: Tensor, d: Tensor, encode_dirs: Callable[[Tensor], Tensor], sigma: Tensor,
                  where: ColourWhere | None = None) -> Tensor:
    """rgb [N, 3] = sigmoid(net([h, encode_dirs(d)])) of the density decoder's outputs h [N, H] and the unit view
    directions d [N, 3]. With `where`, only the samples where(sigma) selects go through the colour decoder and
    the others get rgb 0: a render whose weights say a sample cannot show skips its decoder."""
    if where is None:
        return torch.sigmoid(net(torch.cat([h, encode_dirs(d)], -1)))
    idx = torch.nonzero(where(sigma)).squeeze(1)
    rgb = h.new_zeros(h.shape[0], 3, dtype=torch.float32)
    rgb[idx] = torch.sigmoid(net(torch.cat([h[idx], encode_dirs(d[idx])], -1))).float()
    return rgb


CHUNK_ROWS = 4096
"""rows of an MLP's input the CPU path pushes through all layers together: a chunk's activations (4096 x 64
floats, 1 MB) stay in the L2 cache between layers and between the forward and backward products."""


def _forward_chunks(x: Tensor, params: tuple[Tensor, ...], keep_hidden: bool) -> tuple[Tensor, list[Tensor]]:
    """Linear-ReLU-...-Linear over `x` chunk by chunk (CHUNK_ROWS; `params` = weight, bias of each layer):
    the output and, with keep_hidden, every hidden layer's output over all rows (else [])."""
    weights, biases = params[0::2], params[1::2]
    n = x.shape[0]
    out = x.new_empty(n, weights[-1].shape[0])
    hidden = [x.new_empty(n if keep_hidden else min(n, CHUNK_ROWS), w.shape[0]) for w in weights[:-1]]
    for s in range(0, n, CHUNK_ROWS):
        h = x[s:s + CHUNK_ROWS]
        rows = slice(s, s + len(h)) if keep_hidden else slice(0, len(h))
        for w, b, buf in zip(weights[:-1], biases[:-1], hidden):
            h = torch.addmm(b, h, w.t(), out=buf[rows]).relu_()
        torch.addmm(biases[-1], h, weights[-1].t(), out=out[s:s + CHUNK_ROWS])
    return out, hidden if keep_hidden else []


class _ChunkedMLP(torch.autograd.Function):
    """Linear-ReLU-...-Linear, forward and backward chunk by chunk (CHUNK_ROWS). The forward keeps every
    hidden layer's output ([rows, hidden] floats each, 18 MB for 72,000 rows of 64); the backward goes through
    the chunks again, accumulating the weight gradients and writing each chunk's input gradient. Same values
    as the layer-by-layer products up to the order of the sums."""

    @staticmethod
    def forward(ctx, x: Tensor, *params: Tensor) -> Tensor:
        out, hidden = _forward_chunks(x, params, keep_hidden=True)
        ctx.save_for_backward(x, *hidden, *params)
        ctx.n_hidden = len(hidden)
        return out

    @staticmethod
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor | None, ...]:
        x, *rest = ctx.saved_tensors
        hidden, params = rest[:ctx.n_hidden], rest[ctx.n_hidden:]
        weights = params[0::2]
        grad_w = [torch.zeros_like(p) for p in params]
        grad_x = torch.empty_like(x) if ctx.needs_input_grad[0] else None
        grad_out = grad_out.contiguous()
        for s in range(0, x.shape[0], CHUNK_ROWS):
            acts = [a[s:s + CHUNK_ROWS] for a in (x, *hidden)]
            g = grad_out[s:s + CHUNK_ROWS]
            for i in range(len(weights) - 1, -1, -1):
                grad_w[2 * i].addmm_(g.t(), acts[i])
                grad_w[2 * i + 1].add_(g.sum(0))
                if i > 0:
                    g = torch.ops.aten.threshold_backward(g @ weights[i], acts[i], 0)
                elif grad_x is not None:
                    torch.mm(g, weights[0], out=grad_x[s:s + CHUNK_ROWS])
        return (grad_x, *(g if need else None for g, need in zip(grad_w, ctx.needs_input_grad[1:])))


class MLP(nn.Sequential):
    """Linear-ReLU-...-Linear as an nn.Sequential (same parameters and state_dict keys). On the CPU, for
    float32 inputs of more than CHUNK_ROWS rows, it runs chunk by chunk (_ChunkedMLP): the thin products of
    a NeRF's decoders (25-64 inputs) then work in the cache, 1.6-1.9x faster than layer by layer over the
    whole batch at one thread (decoders of a 72,000-sample step, forward and backward). Elsewhere (CUDA,
    autocast, small batches) the layers run one by one."""

    def forward(self, x: Tensor) -> Tensor:
        if (x.device.type != "cpu" or x.dtype != torch.float32 or x.dim() != 2 or x.shape[0] <= CHUNK_ROWS
                or torch.is_autocast_enabled("cpu")):
            return super().forward(x)
        params = [p for layer in self if isinstance(layer, nn.Linear) for p in (layer.weight, layer.bias)]
        if torch.is_grad_enabled() and (x.requires_grad or any(p.requires_grad for p in params)):
            return _ChunkedMLP.apply(x, *params)
        return _forward_chunks(x, tuple(params), keep_hidden=False)[0]


def mlp(n_in: int, hidden: int, n_hidden: int, n_out: int) -> MLP:
    """n_hidden ReLU layers of width `hidden`, then a linear layer to n_out."""
    layers: list[nn.Module] = []
    d = n_in
    for _ in range(n_hidden):
        layers += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    layers.append(nn.Linear(d, n_out))
    return MLP(*layers)


def param_count(module: nn.Module) -> int:
    """Trainable parameters of a module."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
