"""One assignment per frame: each pixel takes the option (background or a candidate fruit) of least cost.

    cost[p, o] = sum over terms t of WEIGHTS[t] * term_t[p, o]        (each term in [0, 1])

docs/fusion.md has the table of the terms (the cost of a fruit and of background) and a worked pixel."""
from __future__ import annotations

import numpy as np

from rowmap.fusion.evidence import Evidence
from rowmap.fusion.settings import Config

WEIGHTS = {"render": 1.0, "detector": 0.8, "shape": 1.5, "surface": 0.6, "order": 1.5}
"""the weight of each term in the cost (render 1 sets the scale)."""
SHAPE_INSIDE = 0.2
"""shape cost of background on a point inside a fruit's sphere, on the half facing the camera."""
UNKNOWN_SHAPE = 0.8
"""shape cost of a fruit without a sphere on a point inside another fruit's sphere (0 elsewhere); with the
weights, between render and render + SHAPE_INSIDE: that fruit takes the pixel, background does not."""


def terms(ev: Evidence, cfg: Config) -> dict[str, np.ndarray]:
    """Each term of the cost, [P, F + 1] (column 0 = background)."""
    n, cols = len(ev.pixels), np.arange(len(ev.ids) + 1)[None]
    out = {"render": ev.confidence[:, None] * (cols != ev.render[:, None])}
    det = np.where(ev.detector[:, None] > 0, cols != ev.detector[:, None], cols == 0)
    out["detector"] = ((ev.detector >= 0)[:, None] & det).astype(np.float64)
    r = ev.radius[None]
    excess = (ev.rel - 1.0 - cfg.margin_m / r) / (cfg.halo_factor - 1.0 + 1e-9)   # radii beyond radius + margin
    front = ~(ev.beyond > cfg.margin_m)
    inside = ((ev.rel <= 1.0 + cfg.margin_m / r) & front).any(1)
    out["shape"] = np.c_[SHAPE_INSIDE * inside,
                         np.where(np.isnan(ev.rel), UNKNOWN_SHAPE * inside[:, None], np.clip(excess, 0.0, 1.0))]
    on = np.isfinite(ev.gap) & front
    surface = np.minimum(np.where(on, ev.gap, np.inf) / cfg.margin_m, 1.0)
    out["surface"] = np.c_[np.ones(n), surface] * on.any(1)[:, None]
    out["order"] = np.c_[np.zeros(n), np.nan_to_num(np.clip((ev.beyond - cfg.margin_m) / r, 0.0, 1.0))]
    return out


def cost(ev: Evidence, cfg: Config) -> np.ndarray:
    """[P, F + 1] the weighted sum of the terms not in cfg.terms_off."""
    total = np.zeros((len(ev.pixels), len(ev.ids) + 1))
    for name, term in terms(ev, cfg).items():
        if name not in cfg.terms_off:
            total += WEIGHTS[name] * term
    return total


def assign(ev: Evidence, cfg: Config) -> np.ndarray:
    """[P] the fruit id of each evidence pixel (0 = background): the argmin of `cost`, ties to the render's
    option."""
    c = cost(ev, cfg)
    c[np.arange(len(c)), ev.render] -= 1e-6
    return np.r_[0, ev.ids][c.argmin(1)]

