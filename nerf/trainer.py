"""Fit one window (the colour phase): the radiance field, the occupancy grid and the training poses, from the
window's images, depths and initial poses; validation poses are registered to the frozen model
periodically, and the validation frames rendered at the end.

Losses: colour MSE on every ray; a depth L1 (weight cfg.depth_loss_weight) only on rays whose poses are
detached, so the pose corrections are moved by the colour loss alone.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nerf._ext import load_permuto_ext
from nerf.config import NerfConfig
from nerf.fields import build_field, param_count
from nerf.metrics import psnr, psnr_from_mse
from nerf.memory import release_freed
from nerf.model import NerfModel, depth_points, init_occupancy
from nerf.occupancy import OccupancyGrid
from nerf.pixel_sampling import GradientCDF, draw_pixels, gradient_cdf
from nerf.poses import PoseCorrection
from nerf.render import Samples, composite, march, pixel_rays, ray_points, transmittance
from nerf.window import WindowData, depth_far_m, parallax_spread, window_scene


class NonFiniteLoss(FloatingPointError):
    """A training step produced a non-finite loss."""


@dataclass
class FitResult:
    model: NerfModel
    poses_c2w: np.ndarray
    """[N, 4, 4] final poses (world metres)."""
    steps: int
    fit_s: float
    val_psnr: dict[int, float]
    """frame id -> PSNR of the rendered validation frame (dB)."""
    train_psnr: float
    samples_per_ray: float
    render_s_per_image: float
    params: int
    history: list[dict] = field(default_factory=list)
    renders: dict[int, dict] = field(default_factory=dict)
    """window frame index -> render_image() output, for the validation frames."""
    shift_weight: float = 0.0
    """weight (per m^2) the fit gave the pose shift penalty (shift_weight())."""


def fused_adam(dev: torch.device) -> bool | None:
    """Adam's fused implementation (one pass over each parameter instead of one per operation) where torch
    has it, else the default."""
    return True if dev.type in ("cpu", "cuda") else None


def with_far_plane(cfg: NerfConfig, depths: np.ndarray) -> NerfConfig:
    """cfg with its far plane resolved: cfg.far_m where set, else derived from the window's depth
    (depth_far_m; never nearer than cfg.near_m allows)."""
    if cfg.far_m > 0:
        return cfg
    return replace(cfg, far_m=max(depth_far_m(depths), 2 * cfg.near_m))


def shift_weight(cfg: NerfConfig, depths: np.ndarray) -> float:
    """Weight (per m^2) of the pose shift penalty for a window with sensor depth [N, H, W] (metres, 0 = none):
    cfg.pose_shift_penalty / parallax_spread(depths)^2, or cfg.pose_shift_penalty unscaled without valid
    depth. Example: penalty 10, spread 0.28/m (an office) -> 124; spread 1.5/m (a near row) -> 4.4."""
    spread = parallax_spread(depths)
    return cfg.pose_shift_penalty / (spread ** 2 if np.isfinite(spread) else 1.0)


def depth_supervised(depths: Tensor, edge_m: float, far_m: float) -> Tensor:
    """[N, H, W] bool: pixels that carry the depth loss: a valid depth below the far plane and, with edge_m > 0,
    no depth edge around it: every 3x3 neighbour valid (sensors lose depth at occlusion boundaries) and
    max - min of the neighbourhood's depths <= edge_m."""
    ok = (depths > 0) & (depths < far_m)
    if edge_m <= 0:
        return ok
    for i in range(len(depths)):  # frame by frame: the pooled copies of a whole window would take gigabytes
        d = torch.where(ok[i], depths[i], torch.zeros_like(depths[i]))   # an invalid neighbour (0): a large range
        ok[i] &= depth_range_3x3(d) <= edge_m
    return ok


def depth_range_3x3(d: Tensor) -> Tensor:
    """max - min of each pixel's 3x3 neighbourhood (within the image) of d [H, W] float32. On the CPU OpenCV's
    dilate and erode (5x faster at 1280x720 than max pooling, the same values); elsewhere
    depth_range_3x3_pooled."""
    if d.device.type != "cpu":
        return depth_range_3x3_pooled(d)
    import cv2

    a, k = d.contiguous().numpy(), np.ones((3, 3), np.uint8)
    return torch.from_numpy(cv2.dilate(a, k) - cv2.erode(a, k))


def depth_range_3x3_pooled(d: Tensor) -> Tensor:
    """depth_range_3x3 by max pooling (any device): the reference of the CPU path."""
    hi = F.max_pool2d(d[None, None], 3, stride=1, padding=1)
    lo = -F.max_pool2d(-d[None, None], 3, stride=1, padding=1)
    return (hi - lo)[0, 0]


def _rays_for(model: NerfModel, poses: PoseCorrection, c2w0: Tensor, k: Tensor, frames: Tensor, u: Tensor, v: Tensor,
              attach: Tensor | None) -> tuple[Tensor, Tensor]:
    """Rays of pixels (u, v) of `frames` through the corrected poses; rows with attach = False detached."""
    c2w = poses.apply(c2w0, frames)
    if attach is not None:
        c2w = torch.where(attach[:, None, None], c2w, c2w.detach())
    return pixel_rays(k[frames], c2w, u, v)


def fit_window(data: WindowData, cfg: NerfConfig, device: str = "cpu",
               progress: Callable[[int, int, dict], None] | None = None, render_val: bool = True) -> FitResult:
    """Fit the window; with render_val (default) also render every validation frame (FitResult.renders,
    val_psnr, samples_per_ray, render_s_per_image). Without it those stay empty/NaN for the caller to fill
    with `validate()` after a later phase (the panoptic one renders colour and panoptic in one pass)."""
    cfg = with_far_plane(cfg, data.depths)
    torch.manual_seed(cfg.seed)
    g = torch.Generator(device="cpu").manual_seed(cfg.seed)
    dev = torch.device(device)
    n, h, w = data.images.shape[:3]
    images = torch.from_numpy(np.ascontiguousarray(data.images)).to(dev)                       # uint8
    depths = torch.from_numpy(np.ascontiguousarray(data.depths, dtype=np.float32)).to(dev)
    depth_ok = depth_supervised(depths, cfg.depth_edge_m, cfg.far_m)
    w_shift = shift_weight(cfg, data.depths) if cfg.refine_poses else 0.0
    k = torch.tensor(data.intrinsics, dtype=torch.float32, device=dev)
    c2w0 = torch.tensor(data.poses_c2w, dtype=torch.float32, device=dev)
    scene = window_scene(data.poses_c2w, data.intrinsics, (w, h), cfg.far_m).to(dev)
    fld = build_field(cfg, scene.scale_m).to(dev)
    grid = OccupancyGrid(scene.lo, scene.hi, cfg.occupancy_res, dev)
    model = NerfModel(cfg, fld, grid, scene, c2w0.clone(), k, (w, h))
    init_occupancy(model, depths, c2w0, k)
    if getattr(fld, "grid", None) is not None:  # each level's table rows: what its vertices near the surfaces use
        fld.grid.size_levels(scene.normalise(depth_points(depths, c2w0, k, cfg.near_m, cfg.far_m)))
    release_freed()  # its per-frame rays and points (hundreds of MB at 1280x720) are not held through the steps
    poses = PoseCorrection(n, scene.scale_m).to(dev)
    train_idx = torch.from_numpy(np.flatnonzero(data.is_train)).to(dev)
    val_idx = torch.from_numpy(np.flatnonzero(~data.is_train)).to(dev)
    opt = torch.optim.Adam([
        *fld.param_groups(cfg),
        {"params": list(poses.parameters()), "lr": cfg.lr_pose if cfg.refine_poses else 0.0},
    ], fused=fused_adam(dev))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: cfg.lr_decay ** min(1.0, s / max(cfg.steps, 1)))
    val_opt = torch.optim.Adam(poses.parameters(), lr=cfg.lr_pose * 3)
    edges = model.edges(dev)
    occ_fn = model.occupied_fn()
    step_m = cfg.cone_angle * 0.5  # the marching step at half a metre
    history: list[dict] = []
    if cfg.field_kind == "permuto":  # build or load the fused kernel before the clock starts: a first build on
        load_permuto_ext(dev.type)   # a fresh machine takes over a minute of compiling, not of fitting
    t0 = time.perf_counter()
    n_rays = cfg.rays_for(w * h)
    n_edge = int(round(n_rays * cfg.edge_ray_share))
    edge_cdf = gradient_cdf(images[train_idx]) if n_edge else None
    val_cdf = gradient_cdf(images[val_idx]) if len(val_idx) and cfg.val_register_edge_share > 0 else None
    for step in range(cfg.steps):
        frames, u, v = draw_pixels(train_idx, n_rays, h, w, g, edge_cdf, n_edge)
        # half the rays move the poses (colour loss only); the other half carry the depth loss, detached
        pose_rays = torch.arange(n_rays, device=dev) % 2 == 0
        pose_on = cfg.refine_poses and step >= cfg.pose_warmup_steps
        o, d = _rays_for(model, poses, c2w0, k, frames, u.float() + 0.5, v.float() + 0.5,
                         pose_rays if pose_on else torch.zeros_like(pose_rays))
        s = march(o, d, edges, occ_fn, jitter=True, max_per_ray=cfg.max_samples_per_ray)
        known = None
        if cfg.train_early_stop > 0:
            s, known = visible_samples(model, o, d, s, cfg.train_early_stop)
        sigma, col, _, _ = model.shade(o, d, s, grid_features=known)
        rgb, depth_sum, left = composite(sigma, col, s)
        target = images[frames, v, u].float() / 255.0
        loss_c = torch.mean((rgb - target) ** 2)
        loss = loss_c
        if cfg.depth_loss_weight > 0:
            dgt = depths[frames, v, u]
            dpred = depth_sum + left * cfg.far_m
            m = (~pose_rays) & depth_ok[frames, v, u]
            if m.any():
                loss = loss + cfg.depth_loss_weight * torch.mean(torch.abs(dpred[m] - dgt[m]))
        if pose_on and w_shift > 0:
            loss = loss + w_shift * shift_cost(poses, train_idx)
        if not torch.isfinite(loss):
            raise NonFiniteLoss(f"non-finite loss ({float(loss.detach())}) at step {step}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if cfg.skip_empty and step > 0 and step % cfg.occupancy_every == 0:
            grid.update(lambda p: fld.density(scene.normalise(p)), step_m, cfg.occupancy_threshold)
        if len(val_idx) and cfg.refine_poses and step >= cfg.pose_warmup_steps and step % cfg.val_register_every == 0:
            register(model, poses, val_opt, c2w0, k, images, val_idx, cfg.val_register_steps, g,
                     edge_cdf=val_cdf, edge_share=cfg.val_register_edge_share, shift_weight=w_shift)
        if step % 50 == 0 or step == cfg.steps - 1:
            rec = {"step": step, "loss": float(loss.detach()),
                   "psnr": psnr_from_mse(max(float(loss_c.detach()), 1e-10)),
                   "occupied": grid.occupied_share(), "samples_per_ray": len(s) / n_rays}
            history.append(rec)
            if progress:
                progress(step + 1, cfg.steps, {"psnr": rec["psnr"]})
    if len(val_idx) and cfg.refine_poses:
        register(model, poses, val_opt, c2w0, k, images, val_idx, cfg.val_register_final_steps, g,
                 anneal=cfg.val_register_anneal, edge_cdf=val_cdf, edge_share=cfg.val_register_edge_share,
                 shift_weight=w_shift)
    fit_s = time.perf_counter() - t0
    with torch.no_grad():
        final = poses.apply(c2w0, torch.arange(n, device=dev)) if cfg.refine_poses else c2w0
    model.poses_c2w = final.detach().clone()
    train_psnr = float(np.mean([h_["psnr"] for h_ in history[-3:]]))
    res = FitResult(model, final.cpu().numpy().astype(np.float64), cfg.steps, fit_s, {}, train_psnr,
                    float("nan"), float("nan"), param_count(fld), history, {}, w_shift)
    if render_val:
        validate(res, data, model.render_image)
    return res


def validate(res: FitResult, data: WindowData, render: Callable[[int], dict]) -> None:
    """Render every validation frame with `render(i)` (a dict with at least rgb [H, W, 3] and samples_per_ray)
    and fill res.renders (in host memory, also from a GPU; rgb as uint8 tensors, 0-255; opacity left out),
    val_psnr, samples_per_ray and render_s_per_image. A render made at a working scale carries its colour at that
    scale as "rgb_working" [h, w, 3] (not kept in res.renders): its PSNR is measured there, against the recorded
    image area-averaged to that size."""
    import cv2

    spr, render_s = [], []
    for i in np.flatnonzero(~data.is_train).tolist():
        t1 = time.perf_counter()
        # to the host: what is stored outlives the fit, and the copy waits for a GPU's render to finish, so the
        # time is the render's, not its launch's
        out = {k: v.cpu() if isinstance(v, torch.Tensor) else v for k, v in render(i).items()}
        render_s.append(time.perf_counter() - t1)
        rgb, image = out.pop("rgb_working", out["rgb"]), data.images[i]
        if rgb.shape[:2] != image.shape[:2]:
            image = cv2.resize(image, (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_AREA)
        # rgb and fruit kept as the 8 bits they are stored as (rowmap.renders.encode rounds alike): a quarter of
        # the memory; opacity not kept (nothing downstream reads it; 3.7 MB a frame at 1280x720)
        res.renders[i] = {**{k: v for k, v in out.items() if k != "opacity"},
                          "rgb": (out["rgb"].clamp(0, 1) * 255).round().to(torch.uint8)}
        if "fruit" in out:
            res.renders[i]["fruit"] = (np.clip(np.asarray(out["fruit"]), 0, 1) * 255).round().astype(np.uint8)
        spr.append(out["samples_per_ray"])
        target = torch.from_numpy(image).to(rgb.device).float() / 255.0
        res.val_psnr[int(data.frame_ids[i])] = psnr(rgb, target)
    res.samples_per_ray = float(np.mean(spr)) if spr else float("nan")
    res.render_s_per_image = float(np.median(render_s)) if render_s else float("nan")


def shift_cost(poses: PoseCorrection, idx: Tensor) -> Tensor:
    """Mean over frames `idx` of the squared distance (m^2) their pose corrections move the camera centres."""
    return poses.shift_m(idx).pow(2).sum(-1).mean()


@torch.no_grad()
def visible_samples(model: NerfModel, o: Tensor, d: Tensor, s: Samples, min_transmittance: float
                    ) -> tuple[Samples, Tensor | None]:
    """The samples whose transmittance T_i (exclusive, from the current density, no gradients) is at least
    `min_transmittance`: the ones a render with early termination would reach; and, for a field with a hash
    grid, the grid's features at them (what model.shade(..., grid_features=) takes instead of encoding the
    same points again), else None."""
    xn = model.scene.normalise(ray_points(o.detach(), d.detach(), s, with_dirs=False)[0])
    grid = getattr(model.field, "grid", None)
    g = grid(xn) if grid is not None else None
    sigma = model.field.density(xn) if g is None else model.field.density(xn, g)
    keep = transmittance(sigma, s.delta, s.ray_index, s.n_rays) >= min_transmittance
    return Samples(s.ray_index[keep], s.t_mid[keep], s.delta[keep], s.n_rays), None if g is None else g[keep]


def register(model: NerfModel, poses: PoseCorrection, opt: torch.optim.Optimizer, c2w0: Tensor, k: Tensor,
             images: Tensor, val_idx: Tensor, steps: int, g: torch.Generator, rays: int = 1024,
             anneal: float = 1.0, edge_cdf: GradientCDF | None = None, edge_share: float = 0.0,
             shift_weight: float = 0.0) -> None:
    """Optimise only the validation poses against the frozen model (colour loss, plus shift_weight (per m^2)
    times shift_cost). The learning rates fall exponentially to `anneal` times their value over the steps
    (and are restored after); an `edge_share` of the rays is drawn from `edge_cdf` (gradient_cdf of
    images[val_idx]), the rest uniformly."""
    fld = model.field
    req = [p.requires_grad for p in fld.parameters()]
    for p in fld.parameters():
        p.requires_grad_(False)
    h, w = images.shape[1:3]
    dev = images.device
    edges = model.edges(dev)
    lr0 = [grp["lr"] for grp in opt.param_groups]
    n_edge = int(round(rays * edge_share)) if edge_cdf is not None else 0
    try:
        for i in range(steps):
            for grp, lr in zip(opt.param_groups, lr0):
                grp["lr"] = lr * anneal ** (i / max(steps - 1, 1))
            frames, u, v = draw_pixels(val_idx, rays, h, w, g, edge_cdf, n_edge)
            o, d = _rays_for(model, poses, c2w0, k, frames, u.float() + 0.5, v.float() + 0.5, None)
            s = march(o, d, edges, model.occupied_fn(), jitter=True, max_per_ray=model.cfg.max_samples_per_ray)
            sigma, col, _, _ = model.shade(o, d, s)
            rgb = composite(sigma, col, s)[0]
            loss = torch.mean((rgb - images[frames, v, u].float() / 255.0) ** 2)
            if shift_weight > 0:
                loss = loss + shift_weight * shift_cost(poses, val_idx)
            opt.zero_grad(set_to_none=True)
            if torch.isfinite(loss):
                loss.backward()
                opt.step()
    finally:
        for p, r in zip(fld.parameters(), req):
            p.requires_grad_(r)
        for grp, lr in zip(opt.param_groups, lr0):
            grp["lr"] = lr
