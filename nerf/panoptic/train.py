"""The panoptic phase of a window's fit.

After the colour phase (nerf/trainer.py) the radiance field, the occupancy grid and the poses are frozen;
this phase trains only the panoptic part (nerf/panoptic/heads.py: delta grid + semantic and instance heads)
from the detector's per-frame segments of the training frames:

    L = w_sem * L_sem + w_inst * L_inst + w_stuff * L_stuff + w_cons * L_cons      (nerf/panoptic/losses.py)

Each step takes a few training frames and rays in each (a share of them on thing segments, so small
fruits are not starved; importance weights keep the semantic loss unbiased), renders them with the frozen
colour field (no gradient: the colour weights are detached anyway, so panoptic losses can move neither
density nor poses), integrates the semantic and instance probabilities, assigns each frame's thing
segments to instance slots with linear_sum_assignment (nerf/panoptic/assignment.py) and takes a step on
the losses. With repeated-ID rejection on, a segment may only take the slots of the sliding window at its
3D position along the trajectory (its rays un-projected with the rendered depth); the slot memory adds a
cost that draws a segment to the slot whose earlier segments lay where it lies (SlotMemory). Stuff labels
weigh `stuff_confidence` in the semantic loss (a missed detection is weak evidence of no fruit).

Samples whose colour weight is below `min_weight` do not reach the panoptic heads (they could move a
ray's distribution by at most that weight); this is what makes the phase cheap.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch

from nerf.config import PanopticConfig
from nerf.fields import param_count
from nerf.model import NerfModel
from nerf.panoptic.assignment import (SlotMemory, SlotWindow, along_track, assign, position_preference, segment_costs,
                                      segment_geometry)
from nerf.panoptic.labels import VOID, WindowLabels
from nerf.panoptic.losses import consistency_loss, instance_loss, semantic_loss
from nerf.panoptic.result import PanopticResult
from nerf.panoptic.samples import panoptic_field, ray_probs, weighted_samples
from nerf.pixel_sampling import LabelPixels
from nerf.render import pixel_rays
from nerf.trainer import NonFiniteLoss


def slot_window_for(labels: WindowLabels, is_train: np.ndarray, depths: np.ndarray, k: np.ndarray,
                    cfg: PanopticConfig) -> tuple[SlotWindow, int]:
    """ID window width from the busiest training frame (+ margin), frustum length = the image's
    horizontal footprint at the median depth of the detected things; slots = 1 + 3 x width unless set."""
    things = np.isin(labels.semantic, cfg.thing_classes)
    busiest = 1
    for i in np.flatnonzero(is_train):
        ids = np.unique(labels.instance[i][things[i]])
        busiest = max(busiest, int((ids > 0).sum()))
    d = depths[things & (depths > 0)]
    if d.size == 0:
        d = depths[depths > 0]
    z = float(np.median(d)) if d.size else 1.0
    w_px = 2 * float(np.median(k[:, 2]))
    frustum_m = max(w_px / float(np.median(k[:, 0])) * z, 1e-3)
    width = busiest + cfg.id_window_margin
    n_slots = cfg.n_slots or 1 + 3 * width
    if n_slots - 1 < 2 * width:
        raise ValueError(f"panoptic.n_slots = {n_slots} is too few for the ID window: the busiest training frame "
                         f"has {busiest} thing segments, so the window is {width} slots wide and needs at least "
                         f"{2 * width + 1} slots; raise panoptic.n_slots or set it to 0 (automatic)")
    return SlotWindow.for_scene(busiest, frustum_m, n_slots, margin=cfg.id_window_margin), n_slots


def fit_panoptic(model: NerfModel, labels: WindowLabels, is_train: np.ndarray, depths: np.ndarray, cfg: PanopticConfig,
                 progress: Callable[[int, int, dict], None] | None = None, seed: int = 0) -> PanopticResult:
    """Train the panoptic part of a fitted window (`model` with its final poses)."""
    t0 = time.perf_counter()
    dev = model.poses_c2w.device
    n, h, w = labels.semantic.shape
    if model.wh != (w, h):
        raise ValueError(f"labels are {w}x{h} but the model renders {model.wh[0]}x{model.wh[1]}")
    train = np.flatnonzero(is_train)
    things_all = np.isin(labels.semantic, cfg.thing_classes) & (labels.instance > 0)
    train = train[[labels.semantic[i].__ne__(VOID).any() for i in train]]
    skip_instances = cfg.instances and len(train) > 0 and not things_all[train].any()
    if skip_instances:  # no fruit detected in the window: nothing to assign, no instance head to train
        cfg = replace(cfg, instances=False, steps=min(cfg.steps, cfg.stuff_only_steps))
    k_np = model.intrinsics.cpu().numpy()
    window, n_slots = slot_window_for(labels, is_train, depths, k_np, cfg)
    pfield = panoptic_field(model, cfg, n_slots).to(dev)
    params = [{"params": list(pfield.semantic.parameters()) + list(pfield.instance.parameters()), "lr": cfg.lr_mlp}]
    if pfield.grid is not None:
        params.append({"params": list(pfield.grid.parameters()), "lr": cfg.lr_grid, "eps": 1e-15})
    shared = cfg.grid_mode == "shared"
    if shared:  # one grid for colour and panoptic: the panoptic losses move the colour grid too
        params.append({"params": model.field.feature_parameters(), "lr": cfg.lr_grid * 0.1, "eps": 1e-15})
    opt = torch.optim.Adam(params)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.1 ** min(1.0, s / max(cfg.steps, 1)))
    rng = np.random.default_rng(seed)
    n_params = param_count(pfield) - (0 if cfg.instances else param_count(pfield.instance))
    result = PanopticResult(pfield, cfg, window if cfg.id_window and cfg.instances else None, n_slots, 0, 0.0, n_params)
    result.instances_skipped = skip_instances
    if len(train) == 0:  # nothing labelled: heads stay untrained, renders say stuff/uniform
        result.fit_s = time.perf_counter() - t0
        return result
    cams = model.poses_c2w[:, :3, 3].detach().cpu().numpy()
    memory = SlotMemory(n_slots)
    sem_t = torch.from_numpy(labels.semantic)
    inst_t = torch.from_numpy(labels.instance)
    pixels = {int(i): LabelPixels(labels.semantic[i] != VOID, things_all[i]) for i in train}
    for step in range(cfg.steps):
        frames = rng.choice(train, size=min(cfg.frames_per_step, len(train)), replace=False)
        draws = [pixels[int(i)].draw(cfg.rays_per_frame, cfg.thing_ray_share, rng) for i in frames]
        fi = torch.from_numpy(np.repeat(frames, [len(p) for p, _ in draws])).long()
        flat = torch.from_numpy(np.concatenate([p for p, _ in draws])).long()
        importance = torch.from_numpy(np.concatenate([q for _, q in draws])).float().to(dev)
        v, u = flat // w, flat % w
        o, d = pixel_rays(model.intrinsics[fi.to(dev)], model.poses_c2w[fi.to(dev)],
                          u.float().to(dev) + 0.5, v.float().to(dev) + 0.5)
        ks = weighted_samples(model, o, d, cfg.min_weight, keep_grad_features=shared, colour=False)
        p_sem, p_inst = ray_probs(pfield, ks)
        sem = sem_t[fi, v, u].to(dev).long()
        inst = inst_t[fi, v, u].to(dev).long()
        conf = torch.from_numpy(labels.confidence_at(fi.numpy(), v.numpy(), u.numpy())).to(dev)
        is_thing = torch.zeros_like(sem, dtype=torch.bool)
        for c in cfg.thing_classes:
            is_thing |= sem == c
        is_thing &= inst > 0
        is_stuff = (sem != VOID) & ~torch.isin(sem, torch.tensor(cfg.thing_classes, device=dev))
        target = torch.full_like(sem, -1)
        target[is_stuff] = 0
        seg_index = torch.full_like(sem, -1)
        n_seg_total = 0
        pts = (o + d * ks.depth[:, None]).detach().cpu().numpy()
        for j, i in enumerate(frames if cfg.instances else []):
            rows = torch.nonzero((fi == int(i)).to(dev) & is_thing).squeeze(1)
            if rows.numel() == 0:
                result.frames_without_things += 1
                continue  # a frame without fruit needs no assignment
            t_assign = time.perf_counter()
            ids, local = torch.unique(inst[rows], return_inverse=True)
            cost = segment_costs(p_inst[rows].detach(), local, len(ids)).cpu().numpy()
            centres, sizes = segment_geometry(pts[rows.cpu().numpy()], local.cpu().numpy(), len(ids))
            allowed = None
            if cfg.id_window:
                along = along_track(np.nan_to_num(centres), cams)
                allowed = window.allowed(along)
                cost = cost + cfg.position_prior * position_preference(window, along)
            if cfg.memory_prior > 0:
                cost = cost + cfg.memory_prior * memory.cost(np.nan_to_num(centres, nan=np.inf), sizes)
            slots = assign(cost, allowed)
            memory.update(slots, centres)
            result.assign_s += time.perf_counter() - t_assign
            result.frames_assigned += 1
            result.assignments += len(ids)
            result.overflow_segments += max(0, len(ids) - (n_slots - 1))
            target[rows] = torch.from_numpy(slots).to(dev)[local]
            seg_index[rows] = local + n_seg_total
            n_seg_total += len(ids)
        conf = torch.where(is_stuff, conf * cfg.stuff_confidence, conf)
        l_sem = semantic_loss(p_sem, sem, conf * importance, void=VOID)
        if cfg.instances:
            l_inst = instance_loss(p_inst, torch.where(is_thing, target, torch.full_like(target, -1)))
            l_stuff = instance_loss(p_inst, torch.where(is_stuff, target, torch.full_like(target, -1)))
            l_cons = consistency_loss(p_inst, seg_index, n_seg_total)
        else:
            l_inst = l_stuff = l_cons = torch.zeros((), device=dev)
        loss = cfg.w_semantic * l_sem + cfg.w_instance * l_inst + cfg.w_stuff * l_stuff + cfg.w_consistency * l_cons
        if not torch.isfinite(loss):
            raise NonFiniteLoss(f"non-finite panoptic loss ({float(loss.detach())}) at panoptic step {step}")
        opt.zero_grad(set_to_none=True)
        if loss.requires_grad:
            loss.backward()
            opt.step()
        sched.step()
        if step % 25 == 0 or step == cfg.steps - 1:
            rec = {"step": step, "loss": float(loss.detach()), "semantic": float(l_sem.detach()),
                   "instance": float(l_inst.detach()), "stuff": float(l_stuff.detach()),
                   "consistency": float(l_cons.detach()), "samples_per_ray": len(ks.w) / max(ks.n_rays, 1)}
            result.history.append(rec)
            if progress:
                progress(step + 1, cfg.steps, {"loss": rec["loss"]})
    result.steps = cfg.steps
    result.fit_s = time.perf_counter() - t0
    return result
