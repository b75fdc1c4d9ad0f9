"""Panoptic rendering of a frame: colour, depth and the panoptic heads' distributions in one pass over the
frozen colour model, then 2D post-processing (nerf/panoptic/post.py)."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from nerf.model import NerfModel
from nerf.panoptic.post import best_slot, labels_from_slots
from nerf.panoptic.result import PanopticResult
from nerf.panoptic.samples import ray_probs, weighted_samples
from nerf.render import pixel_rays


@torch.no_grad()
def render_panoptic(model: NerfModel, pres: PanopticResult, i: int | None = None, c2w: Tensor | None = None,
                    k: Tensor | None = None, chunk: int = 8192) -> dict:
    """Render frame i (or a given pose): rgb [H, W, 3], depth [H, W] (m), opacity, semantic [H, W] uint8,
    instance [H, W] int32 (window slots, 0 = stuff), after post-processing; fruit [H, W] float32, the thing
    classes' probability before it (a fruit's sliver the post-processing drops keeps it); samples_per_ray."""
    w, h = model.wh
    c2w, k, u, v = model.image_pixels(i, c2w, k)
    cfg = pres.cfg
    rgb, depth, opac, p_sem, slot = [], [], [], [], []
    n_eval = 0
    for s in range(0, u.shape[0], chunk):
        uu, vv = u[s:s + chunk], v[s:s + chunk]
        o, d = pixel_rays(k.expand(uu.shape[0], 4), c2w.expand(uu.shape[0], 4, 4), uu, vv)
        ks = weighted_samples(model, o, d, cfg.min_weight)
        ps, pi = ray_probs(pres.field, ks)
        rgb.append(ks.rgb)
        depth.append(ks.depth)
        opac.append(ks.opacity)
        p_sem.append(ps)
        slot.append(best_slot(pi.cpu().numpy()))  # not the [pixels, slots] distributions: 0.4 GB at 1280x720
        n_eval += ks.n_evaluated
    p_sem_img = torch.cat(p_sem).reshape(h, w, -1).cpu().numpy()
    depth_img = torch.cat(depth).reshape(h, w)
    sem, inst = labels_from_slots(p_sem_img, np.concatenate(slot).reshape(h, w), cfg, depth_img.cpu().numpy())
    fruit = p_sem_img[..., list(cfg.thing_classes)].sum(-1).astype(np.float32)
    return {"rgb": torch.cat(rgb).reshape(h, w, 3), "depth": depth_img,
            "opacity": torch.cat(opac).reshape(h, w), "semantic": sem, "instance": inst, "fruit": fruit,
            "samples_per_ray": n_eval / (h * w)}
