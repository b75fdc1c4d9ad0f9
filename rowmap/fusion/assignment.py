"""One assignment per frame: each pixel takes the option (background or a candidate fruit) of least cost.

    cost[p, o] = sum over terms t of WEIGHTS[t] * term_t[p, o]        (each term in [0, 1])

| term     | option o = fruit f                                   | o = background                       |
|----------|------------------------------------------------------|--------------------------------------|
| render   | confidence[p] if the render does not paint f at p    | confidence[p] if it paints a fruit   |
| detector | 1 if p's segment belongs to another fruit            | 1 if p lies in a detector segment    |
| shape    | 0 within radius + margin_m of f's sphere centre,     | SHAPE_INSIDE if p lies on the front  |
|          | rising to 1 at halo_factor x radius + margin_m;      | half of some fruit's sphere          |
|          | UNKNOWN_SHAPE where f has no sphere and p lies in    |                                      |
|          | another's                                            |                                      |
| surface  | distance to f's seen surface / margin_m (at most 1), | 1                                    |
|          | where p lies on some fruit's seen surface            |                                      |
| order    | 0 up to margin_m beyond f's centre along the ray,    | 0                                    |
|          | rising to 1 a radius further (f would hide p)        |                                      |

Worked example (weights as below): a leaf pixel that the render paints as fruit f (the halo around its
silhouette), 1.4 radii from f's centre, in no detector segment: f costs shape 1.5 x 1 = 1.5, background costs
render 1.0; the pixel becomes background. Were it in f's detector segment, background would cost 1.0 + 0.8
and the pixel would stay f."""
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
    n, m = len(ev.pixels), len(ev.ids) + 1
    cols = np.arange(m)[None]
    out = {"render": ev.confidence[:, None] * (cols != ev.render[:, None])}
    has_seg = ev.detector >= 0
    det = np.where(ev.detector[:, None] > 0, cols != ev.detector[:, None], cols == 0)
    out["detector"] = (has_seg[:, None] & det).astype(np.float64)
    r = ev.radius[None]
    excess = (ev.rel - 1.0 - cfg.margin_m / r) / (cfg.halo_factor - 1.0 + 1e-9)   # radii beyond radius + margin
    front = ~(ev.beyond > cfg.margin_m)
    inside = (ev.rel <= 1.0 + cfg.margin_m / r) & front
    shape = np.zeros((n, m))
    shape[:, 1:] = np.where(np.isnan(ev.rel), UNKNOWN_SHAPE * inside.any(1)[:, None], np.clip(excess, 0.0, 1.0))
    shape[:, 0] = SHAPE_INSIDE * inside.any(1)
    out["shape"] = shape
    on = np.isfinite(ev.gap) & front
    surface = np.zeros((n, m))
    surface[:, 1:] = np.minimum(np.where(on, ev.gap, np.inf) / cfg.margin_m, 1.0)
    surface[:, 0] = 1.0
    out["surface"] = surface * on.any(1)[:, None]
    order = np.zeros((n, m))
    order[:, 1:] = np.nan_to_num(np.clip((ev.beyond - cfg.margin_m) / r, 0.0, 1.0))
    out["order"] = order
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

