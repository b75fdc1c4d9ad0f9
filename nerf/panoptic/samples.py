"""What the panoptic heads see of a ray batch: march the frozen colour model with early termination, keep the
samples that carry colour weight (KeptSamples), and integrate the heads' probabilities over them."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nerf.config import PanopticConfig
from nerf.model import NerfModel
from nerf.panoptic.heads import PanopticField, integrate_probs
from nerf.render import HeavySamples, Rounds, round_size


def panoptic_field(model: NerfModel, cfg: PanopticConfig, n_slots: int) -> PanopticField:
    """The panoptic part sized after the colour grid of `model`; a field without a hash grid (Field.grid None)
    gets heads on its features alone, which only grid_mode 'shared' allows."""
    mc = model.cfg
    enc = model.field.grid
    if enc is None:
        if cfg.grid_mode != "shared":
            raise ValueError(f"the {mc.field_kind} field has no hash grid: panoptic grid_mode must be 'shared', got "
                             f"{cfg.grid_mode!r}")
        return PanopticField(1, model.field.feature_dim, 1, 1.0, 1.0, cfg.n_classes, n_slots, mode="shared",
                             hidden=cfg.hidden)
    cap = mc.log2_capacity_delta if cfg.grid_mode == "delta" else mc.log2_capacity
    return PanopticField(mc.n_levels, mc.n_features, cap, float(enc.scales[0]), float(enc.scales[-1]), cfg.n_classes,
                         n_slots, mode=cfg.grid_mode, hidden=cfg.hidden, seed=mc.seed + 1)


@dataclass
class KeptSamples:
    """Samples of a ray batch that carry colour weight, with what the panoptic heads need."""

    x: Tensor        # [S, 3] normalised positions
    g: Tensor        # [S, L*F] colour-grid features (detached unless the grid is shared)
    w: Tensor        # [S] colour weights (detached)
    ray_index: Tensor
    n_rays: int
    rgb: Tensor | None   # [R, 3]; None where weighted_samples was asked for no colour
    depth: Tensor    # [R] z-depth, metres (expected termination depth / opacity)
    opacity: Tensor  # [R]
    n_evaluated: int


def weighted_samples(model: NerfModel, o: Tensor, d: Tensor, min_weight: float, round_samples: int = 32,
                     keep_grad_features: bool = False, colour: bool = True) -> KeptSamples:
    """March rays through the frozen colour model in rounds with early termination, as rendering does (8, 16,
    then `round_samples` occupied samples per ray: most rays meet an opaque surface within their first few),
    and keep the samples with weight >= min_weight. colour False: no ray colour (the panoptic phase's training
    steps need only the weights, depth and features; the colour decoder is a third of shading a sample)."""
    n = o.shape[0]
    dev = o.device
    cfg = model.cfg
    edges = model.edges(dev)
    occ = model.occupied_fn()
    eps = cfg.early_stop_transmittance
    rgb = torch.zeros(n, 3, device=dev) if colour else None
    depth = torch.zeros(n, device=dev)
    trans = torch.ones(n, device=dev)
    active = torch.arange(n, device=dev)
    xs, gs, ws, rs = [], [], [], []
    n_eval = 0
    with torch.no_grad():
        rounds = Rounds(o, d, edges, occ)
    first = 0
    while active.numel():
        per_ray = round_size(first, round_samples, cfg.skip_empty)
        with torch.no_grad():
            s = rounds.take(active, first, per_ray)
        first += per_ray
        if len(s) == 0:
            break
        heavy = HeavySamples(s, trans[active])
        with torch.set_grad_enabled(keep_grad_features):
            sigma, col, x, g = model.shade(o[active], d[active], s, colour, colour_where=heavy if colour else None)
        with torch.no_grad():
            if heavy.weights is None:
                heavy(sigma)
            w, left = heavy.weights, heavy.left
            ray = active[s.ray_index]
            if colour:
                rgb.index_add_(0, ray, w[:, None] * col.detach())
            depth.index_add_(0, ray, w * s.t_mid)
            keep = w >= min_weight
            had = torch.bincount(s.ray_index, minlength=s.n_rays) >= per_ray
            trans[active] = trans[active] * left
        xs.append(model.scene.normalise(x.detach()[keep]))
        gs.append(g[keep] if keep_grad_features else g.detach()[keep])
        ws.append(w[keep])
        rs.append(ray[keep])
        n_eval += len(s)
        active = active[had & (trans[active] > eps)]
    opacity = 1 - trans
    width = model.field.feature_dim
    cat = lambda parts, shape: torch.cat(parts) if parts else torch.zeros(shape, device=dev)  # noqa: E731
    ray_index = cat(rs, (0,)).long()
    order = torch.argsort(ray_index, stable=True)
    return KeptSamples(cat(xs, (0, 3))[order], cat(gs, (0, width))[order], cat(ws, (0,))[order], ray_index[order], n,
                       rgb, depth / opacity.clamp_min(1e-6), opacity, n_eval)


def ray_probs(pfield: PanopticField, ks: KeptSamples) -> tuple[Tensor, Tensor]:
    """Per-ray semantic [R, D] and instance [R, N] distributions (rows sum to 1)."""
    if len(ks.w) == 0:
        d, n = pfield.semantic[-1].out_features, pfield.instance[-1].out_features
        return torch.full((ks.n_rays, d), 1.0 / d), torch.full((ks.n_rays, n), 1.0 / n)
    sem_logits, inst_logits = pfield(ks.x, ks.g)
    return (integrate_probs(sem_logits, ks.w, ks.ray_index, ks.n_rays),
            integrate_probs(inst_logits, ks.w, ks.ray_index, ks.n_rays))
