"""Which pixels a training step draws rays through.

Colour (and pose registration): uniform over the frames' pixels, with a share drawn in proportion to the
image's colour gradient magnitude (`gradient_cdf`, `draw_pixels`). Panoptic: per frame, a share on the
detected thing segments and the rest over the labelled pixels, with importance weights that undo the
oversampling (`LabelPixels`). Both draw from one seeded generator each (torch for the colour phase,
numpy for the panoptic phase), so a fit is reproducible from its seed.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


CDF_BLOCK = 64
"""Pixels per block of a GradientCDF: the cumulative sum is kept at each block's end only."""


class GradientCDF:
    """The cumulative distribution of per-pixel weights [M] (flattened frames), held as the float32 weights and
    the float64 cumulative sum at the end of every CDF_BLOCK-th pixel: about half the memory of the whole
    float64 sum (at 1280x720 that sum is 7.4 MB per frame). A draw finds its block from the block ends, then
    its pixel by summing the block's weights from the block's start, sequentially in float64 as the whole sum
    runs, so every draw is the one a search of the whole sum would make (tested)."""

    def __init__(self, weights: Tensor):
        self.weights = weights.reshape(-1)                                  # float32 [M]
        m = self.weights.shape[0]
        pad = (-m) % CDF_BLOCK
        ends, carry = [], torch.zeros(1, dtype=torch.float64, device=weights.device)
        step = CDF_BLOCK * 4096
        for s in range(0, m, step):  # chunk by chunk, each carried on from the last: one sequential sum
            c = torch.cumsum(torch.cat([carry, self.weights[s:s + step].double()]), 0)[1:]
            ends.append(c[CDF_BLOCK - 1::CDF_BLOCK])
            carry = c[-1:]
        if pad:
            ends.append(carry)                                              # the last, partial block's end
        self.block_end = torch.cat(ends)                                    # float64 [ceil(M / CDF_BLOCK)]
        self.total = carry

    def __len__(self) -> int:
        return self.weights.shape[0]

    def search(self, u: Tensor) -> Tensor:
        """For values u [n] (float64): the first flat index whose cumulative sum is >= u (len(self) past the end)."""
        m, nb = len(self), self.block_end.shape[0]
        b = torch.searchsorted(self.block_end, u).clamp_max(nb - 1)
        start = b * CDF_BLOCK
        cols = start[:, None] + torch.arange(CDF_BLOCK, device=u.device)
        w = torch.where(cols < m, self.weights[cols.clamp_max(m - 1)], 0.0).double()
        base = torch.where(b > 0, self.block_end[(b - 1).clamp_min(0)], torch.zeros_like(u))
        cum = torch.cumsum(torch.cat([base[:, None], w], 1), 1)[:, 1:].contiguous()  # the block's part of the sum
        j = torch.searchsorted(cum, u[:, None].contiguous()).squeeze(1)
        return torch.where(u > self.block_end[-1], torch.full_like(start, m), (start + j).clamp_max(m))


def gradient_cdf(images: Tensor) -> GradientCDF:
    """Cumulative sum over [N, H, W] (flattened) of each pixel's colour gradient magnitude (central
    differences, summed over channels) plus a small floor, for drawing pixels near texture and edges."""
    n, h, w = images.shape[:3]
    mag = torch.empty((n, h, w), dtype=torch.float32, device=images.device)
    for i in range(n):  # frame by frame: float copies of a whole window's images would take gigabytes
        mag[i] = gradient_magnitude(images[i])
    mag = mag.reshape(-1)
    mag += 0.05 * mag.mean()
    return GradientCDF(mag)


def gradient_magnitude(image: Tensor) -> Tensor:
    """|d/du| + |d/dv| of an [H, W, C] uint8 image scaled to [0, 1] (central differences, 0 at the border), summed
    over channels -> [H, W] float32. On the CPU in numpy with fewer temporaries (2.4x faster at 1280x720, the same
    float32 operations in the same order, so the same bits); elsewhere gradient_magnitude_torch."""
    if image.device.type != "cpu":
        return gradient_magnitude_torch(image)
    x = image.numpy().astype(np.float32) / np.float32(255.0)
    s = np.zeros_like(x)
    s[:, 1:-1] = np.abs((x[:, 2:] - x[:, :-2]) * np.float32(0.5))
    s[1:-1] += np.abs((x[2:] - x[:-2]) * np.float32(0.5))
    out = s[..., 0].copy()
    for c in range(1, s.shape[-1]):
        out += s[..., c]
    return torch.from_numpy(out)


def gradient_magnitude_torch(image: Tensor) -> Tensor:
    """gradient_magnitude in torch on any device: the reference of the CPU path."""
    x = image.float() / 255.0
    gx = torch.zeros_like(x)
    gy = torch.zeros_like(x)
    gx[:, 1:-1] = (x[:, 2:] - x[:, :-2]) / 2
    gy[1:-1] = (x[2:] - x[:-2]) / 2
    return (gx.abs() + gy.abs()).sum(-1)


def draw_from_cdf(cdf: GradientCDF, n: int, g: torch.Generator) -> Tensor:
    """n flat indices drawn with probability proportional to the weights of `cdf` (gradient_cdf)."""
    u = torch.rand(n, generator=g, dtype=torch.float64).to(cdf.weights.device) * cdf.total
    return cdf.search(u).clamp_max(len(cdf) - 1)


def draw_pixels(idx: Tensor, n: int, h: int, w: int, g: torch.Generator, cdf: GradientCDF | None = None,
                n_edge: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """n pixels (frames, u, v) of the frames `idx` of [N, H, W] images: the first n_edge drawn from `cdf`
    (gradient_cdf of images[idx]), the rest uniformly."""
    dev = idx.device
    frames = idx[torch.randint(0, len(idx), (n,), generator=g).to(dev)]
    u = torch.randint(0, w, (n,), generator=g).to(dev)
    v = torch.randint(0, h, (n,), generator=g).to(dev)
    if n_edge and cdf is not None:
        pick = draw_from_cdf(cdf, n_edge, g)
        frames[:n_edge], v[:n_edge], u[:n_edge] = idx[pick // (h * w)], (pick // w) % h, pick % w
    return frames, u, v


class LabelPixels:
    """One frame's labelled pixels [H, W] and thing pixels [H, W], indexed once for the panoptic steps' draws, so
    a step does not scan the full-size masks. The labelled pixels are not listed (a 1280x720 frame's would be 3.7
    MB): the k-th is k plus the unlabelled pixels before it, found in the sorted list of those (few)."""

    def __init__(self, labelled: np.ndarray, things: np.ndarray):
        self.things = things.ravel()
        self.thing_px = np.flatnonzero(things)
        void = np.flatnonzero(~labelled.ravel())
        self.size = labelled.size
        self.n_labelled = self.size - len(void)
        # unlabelled pixel j has void[j] - j labelled pixels before it (none labelled: every pixel is the pool)
        self._gaps = void - np.arange(len(void)) if self.n_labelled else np.zeros(0, np.int64)

    def labelled_pixel(self, k: np.ndarray) -> np.ndarray:
        """Flat index of the k-th labelled pixel (the k-th pixel where none is labelled), k [n] ints."""
        return k + np.searchsorted(self._gaps, k, side="right")

    def draw(self, n: int, share: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Flat pixel indices [n], `share` of them on thing pixels and the rest over the labelled pixels (all pixels
        if none is), with each draw's importance weight p/q (p = uniform over labelled pixels, q = the mixture
        actually sampled; scaled to a maximum of 1: the semantic loss takes weights in [0, 1]), so a loss
        weighted by it sees the labels in their true proportions."""
        pool_size = self.n_labelled or self.size
        n_thing = int(round(n * share)) if self.thing_px.size else 0
        s = n_thing / n
        picks = [self.thing_px[rng.integers(0, self.thing_px.size, n_thing)]] if n_thing else []
        picks.append(self.labelled_pixel(rng.integers(0, pool_size, n - n_thing)))
        px = np.concatenate(picks)
        q = (1 - s) / pool_size + np.where(self.things[px], s / max(self.thing_px.size, 1), 0.0)
        w = (1.0 / pool_size) / q
        return px, w / w.max()
