"""Which pixels a training step draws rays through.

Colour (and pose registration): uniform over the frames' pixels, with a share drawn in proportion to the
image's colour gradient magnitude (`gradient_cdf`, `draw_pixels`). Panoptic: per frame, a share on the
detected thing segments and the rest over the labelled pixels, with importance weights that undo the
oversampling (`draw_label_pixels`). Both draw from one seeded generator each (torch for the colour phase,
numpy for the panoptic phase), so a fit is reproducible from its seed.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def gradient_cdf(images: Tensor) -> Tensor:
    """Cumulative sum over [N, H, W] (flattened) of each pixel's colour gradient magnitude (central
    differences, summed over channels) plus a small floor, for drawing pixels near texture and edges."""
    n, h, w = images.shape[:3]
    mag = torch.empty((n, h, w), dtype=torch.float32, device=images.device)
    for i in range(n):  # frame by frame: float copies of a whole window's images would take gigabytes
        x = images[i].float() / 255.0
        gx = torch.zeros_like(x)
        gy = torch.zeros_like(x)
        gx[:, 1:-1] = (x[:, 2:] - x[:, :-2]) / 2
        gy[1:-1] = (x[2:] - x[:-2]) / 2
        mag[i] = (gx.abs() + gy.abs()).sum(-1)
    mag = mag.reshape(-1)
    mag += 0.05 * mag.mean()
    return mag.double().cumsum_(0)


def draw_from_cdf(cdf: Tensor, n: int, g: torch.Generator) -> Tensor:
    """n flat indices drawn with probability proportional to the increments of `cdf` (gradient_cdf)."""
    u = torch.rand(n, generator=g, dtype=torch.float64).to(cdf.device) * cdf[-1]
    return torch.searchsorted(cdf, u).clamp_max(cdf.shape[0] - 1)


def draw_pixels(idx: Tensor, n: int, h: int, w: int, g: torch.Generator, cdf: Tensor | None = None,
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


def draw_label_pixels(labelled: np.ndarray, things: np.ndarray, n: int, share: float,
                      rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices of one frame, `share` of them on `things` pixels [H, W] and the rest over the
    `labelled` pixels [H, W] (all pixels if none is), with each draw's importance weight p/q (p = uniform over
    labelled pixels, q = the mixture actually sampled; scaled to a maximum of 1), so a loss weighted by it
    sees the labels in their true proportions."""
    thing_px = np.flatnonzero(things)
    labelled_px = np.flatnonzero(labelled)
    pool = labelled_px if labelled_px.size else np.arange(labelled.size)
    n_thing = int(round(n * share)) if thing_px.size else 0
    s = n_thing / n
    picks = [thing_px[rng.integers(0, thing_px.size, n_thing)]] if n_thing else []
    picks.append(pool[rng.integers(0, pool.size, n - n_thing)])
    px = np.concatenate(picks)
    on_thing = things.ravel()[px]
    q = (1 - s) / pool.size + np.where(on_thing, s / max(thing_px.size, 1), 0.0)
    w = (1.0 / pool.size) / q
    return px, w / w.max()  # <= 1: the semantic loss takes weights in [0, 1]
