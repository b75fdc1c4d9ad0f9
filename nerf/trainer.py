"""Fit one window: the radiance field, the occupancy grid and the train poses, from the window's images,
depths and odometry poses; validation poses are registered to the frozen model periodically.

Losses: colour MSE on every ray; a depth L1 (weight cfg.depth_loss_weight) only on rays whose poses are
detached, so the pose corrections are moved by the colour loss alone.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nerf._ext import load_permuto_ext
from nerf.config import NerfConfig
from nerf.field import RadianceField, build_field, param_count
from nerf.occupancy import OccupancyGrid
from nerf.poses import PoseCorrection
from nerf.render import (Rounds, Samples, accumulate, composite_weights, cone_steps, depth_guided, march, pixel_rays,
                         transmittance)


class NonFiniteLoss(FloatingPointError):
    """A training step produced a non-finite loss."""


@dataclass
class WindowData:
    images: np.ndarray
    """[N, H, W, 3] uint8 RGB."""
    depths: np.ndarray
    """[N, H, W] float32 metres, 0 = invalid."""
    intrinsics: np.ndarray
    """[N, 4] fx, fy, cx, cy."""
    poses_c2w: np.ndarray
    """[N, 4, 4] initial camera-to-world poses (OpenCV camera)."""
    is_train: np.ndarray
    """[N] bool."""
    frame_ids: np.ndarray
    """[N] frame ids (for messages)."""

    def __post_init__(self) -> None:
        n = len(self.images)
        for name in ("depths", "intrinsics", "poses_c2w", "is_train", "frame_ids"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"WindowData.{name} has {len(getattr(self, name))} entries, images have {n}")
        if not self.is_train.any():
            raise ValueError("a window needs at least one training frame")
        if not np.isfinite(self.poses_c2w).all():
            raise ValueError("a window's initial poses contain non-finite values")

    def take(self, idx: np.ndarray) -> "WindowData":
        """The window with only the frames `idx` (indices into its frames), in that order."""
        return WindowData(self.images[idx], self.depths[idx], self.intrinsics[idx], self.poses_c2w[idx],
                          self.is_train[idx], self.frame_ids[idx])


@dataclass
class Scene:
    """Normalisation of the window: field input = (x - centre) / scale_m; bounds in metres."""

    centre: Tensor
    scale_m: float
    lo: Tensor
    hi: Tensor

    def normalise(self, x: Tensor) -> Tensor:
        return (x - self.centre) / self.scale_m


def window_scene(poses: np.ndarray, k: np.ndarray, wh: tuple[int, int], far_m: float) -> Scene:
    """Bounds = the box around every camera centre and its frustum corners at `far_m`."""
    w, h = wh
    pts = [poses[:, :3, 3]]
    for u, v in ((0, 0), (w, 0), (0, h), (w, h)):
        d = np.stack([(u - k[:, 2]) / k[:, 0], (v - k[:, 3]) / k[:, 1], np.ones(len(k))], -1)
        pts.append(poses[:, :3, 3] + np.einsum("nij,nj->ni", poses[:, :3, :3], d) * far_m)
    pts = np.concatenate(pts)
    lo, hi = pts.min(0) - 0.05, pts.max(0) + 0.05
    centre = (lo + hi) / 2
    scale = float((hi - lo).max() / 2)
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return Scene(t(centre), scale, t(lo), t(hi))


@dataclass
class NerfModel:
    """Everything needed to render a window again: field, occupancy grid, normalisation, poses."""

    cfg: NerfConfig
    field: RadianceField
    grid: OccupancyGrid
    scene: Scene
    poses_c2w: Tensor
    intrinsics: Tensor
    wh: tuple[int, int]
    extras: dict = field(default_factory=dict)

    def state(self) -> dict:
        return {"cfg": asdict(self.cfg), "field": self.field.state_dict(), "grid": self.grid.state_dict(),
                "scene": {"centre": self.scene.centre, "scale_m": self.scene.scale_m, "lo": self.scene.lo,
                          "hi": self.scene.hi},
                "poses_c2w": self.poses_c2w, "intrinsics": self.intrinsics, "wh": self.wh, "extras": self.extras}

    @classmethod
    def from_state(cls, state: dict, device: str = "cpu") -> "NerfModel":
        cfg = NerfConfig(**state["cfg"])
        sc = state["scene"]
        scene = Scene(sc["centre"].to(device), sc["scale_m"], sc["lo"].to(device), sc["hi"].to(device))
        fld = build_field(cfg, scene.scale_m).to(device)
        fld.load_state_dict(state["field"])
        return cls(cfg, fld, OccupancyGrid.from_state({k: v.to(device) for k, v in state["grid"].items()}), scene,
                   state["poses_c2w"].to(device), state["intrinsics"].to(device), tuple(state["wh"]),
                   state.get("extras", {}))

    def edges(self, device) -> Tensor:
        step = self.cfg.step_scale / float(self.intrinsics[:, 0].mean())
        return cone_steps(self.cfg.near_m, self.cfg.far_m, step, device, self.cfg.max_step_m)

    def occupied_fn(self):
        if self.cfg.skip_empty:
            return self.grid
        lo, hi = self.scene.lo, self.scene.hi
        return lambda p: ((p >= lo) & (p <= hi)).all(-1)

    def shade(self, o: Tensor, d: Tensor, s: Samples) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Field at packed samples -> (sigma [S], rgb [S, 3], world points [S, 3], g_c [S, L*F])."""
        x = o[s.ray_index] + d[s.ray_index] * s.t_mid[:, None]
        dn = torch.nn.functional.normalize(d[s.ray_index], dim=-1)
        sigma, rgb, g = self.field(self.scene.normalise(x), dn)
        return sigma, rgb, x, g

    @torch.no_grad()
    def render_rays(self, o: Tensor, d: Tensor, round_samples: int = 32) -> dict[str, Tensor]:
        """Render rays in rounds of occupied samples per ray (8, 16, then `round_samples` each: most rays
        meet an opaque surface within their first few occupied samples), dropping rays whose
        transmittance fell below cfg.early_stop_transmittance (or that have no samples left)."""
        n = o.shape[0]
        edges = self.edges(o.device)
        occ = self.occupied_fn()
        rgb = torch.zeros(n, 3, device=o.device)
        depth = torch.zeros(n, device=o.device)
        trans = torch.ones(n, device=o.device)
        active = torch.arange(n, device=o.device)
        n_samples = 0
        eps = self.cfg.early_stop_transmittance
        first = 0
        rounds = Rounds(o, d, edges, occ)
        while active.numel():
            per_ray = min(round_samples, 8 << min(first // 8, 2)) if self.cfg.skip_empty else round_samples
            s = rounds.take(active, first, per_ray)
            first += per_ray
            if len(s) == 0:
                break
            sigma, col, _, _ = self.shade(o[active], d[active], s)
            w, left = composite_weights(sigma, s.delta, s.ray_index, s.n_rays)
            w = w * trans[active][s.ray_index]
            rgb.index_add_(0, active, accumulate(col, w, s.ray_index, s.n_rays))
            depth.index_add_(0, active, accumulate(s.t_mid, w, s.ray_index, s.n_rays))
            had = torch.bincount(s.ray_index, minlength=s.n_rays) >= per_ray
            trans[active] = trans[active] * left
            n_samples += len(s)
            active = active[had & (trans[active] > eps)]
        opacity = 1 - trans
        return {"rgb": rgb, "depth": depth / opacity.clamp_min(1e-6), "opacity": opacity,
                "samples_per_ray": torch.tensor(n_samples / max(n, 1))}

    def image_pixels(self, i: int | None = None, c2w: Tensor | None = None,
                     k: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Pose and intrinsics of frame i (or the given ones) and the pixel centres u, v [H*W] of a full image."""
        w, h = self.wh
        c2w = self.poses_c2w[i] if c2w is None else c2w
        k = self.intrinsics[i] if k is None else k
        dev = c2w.device
        v, u = torch.meshgrid(torch.arange(h, device=dev) + 0.5, torch.arange(w, device=dev) + 0.5, indexing="ij")
        return c2w, k, u.reshape(-1), v.reshape(-1)

    @torch.no_grad()
    def render_image(self, i: int | None = None, c2w: Tensor | None = None, k: Tensor | None = None) -> dict[str, Tensor]:
        """Full image of frame i (or of a given pose/intrinsics): rgb [H, W, 3], depth [H, W], opacity."""
        w, h = self.wh
        c2w, k, u, v = self.image_pixels(i, c2w, k)
        outs = {"rgb": [], "depth": [], "opacity": []}
        total = 0.0
        for s in range(0, u.shape[0], self.cfg.chunk_rays):
            uu, vv = u[s:s + self.cfg.chunk_rays], v[s:s + self.cfg.chunk_rays]
            o, d = pixel_rays(k.expand(uu.shape[0], 4), c2w.expand(uu.shape[0], 4, 4), uu, vv)
            r = self.render_rays(o, d)
            total += float(r["samples_per_ray"]) * uu.shape[0]
            for key in outs:
                outs[key].append(r[key])
        out = {key: torch.cat(v).reshape(h, w, -1).squeeze(-1) for key, v in outs.items()}
        out["samples_per_ray"] = total / (h * w)
        return out


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


def fused_adam(dev: torch.device) -> bool | None:
    """Adam's fused implementation (one pass over each parameter instead of one per operation: 2 vs 9 ms
    per step for a 1.3 M-entry table on one core) where torch has it, else the default."""
    return True if dev.type in ("cpu", "cuda") else None


def psnr(a: Tensor, b: Tensor) -> float:
    mse = float(torch.mean((a.float() - b.float()) ** 2))
    return float("inf") if mse == 0 else -10 * math.log10(mse)


def depth_weight(cfg: NerfConfig, step: int) -> float:
    """Depth loss weight at `step`: cfg.depth_loss_weight, falling linearly to 0 over the first
    cfg.depth_loss_fade share of the steps when that is > 0."""
    if cfg.depth_loss_fade <= 0:
        return cfg.depth_loss_weight
    return cfg.depth_loss_weight * max(0.0, 1.0 - step / (cfg.depth_loss_fade * cfg.steps))


def depth_supervised(depths: Tensor, edge_m: float, far_m: float) -> Tensor:
    """[N, H, W] bool: pixels that carry the depth loss: a valid depth below the far plane and, with edge_m > 0,
    no depth edge around it: every 3x3 neighbour valid (sensors lose depth at occlusion boundaries) and
    max - min of the neighbourhood's depths <= edge_m."""
    ok = (depths > 0) & (depths < far_m)
    if edge_m <= 0:
        return ok
    d = torch.where(ok, depths, torch.zeros_like(depths))[:, None]
    hi = F.max_pool2d(d, 3, stride=1, padding=1)
    lo = -F.max_pool2d(-d, 3, stride=1, padding=1)       # an invalid neighbour (0) makes the range large
    return ok & ((hi - lo)[:, 0] <= edge_m)


def gradient_cdf(images: Tensor) -> Tensor:
    """Cumulative sum over [N, H, W] (flattened) of each pixel's colour gradient magnitude (central
    differences, summed over channels) plus a small floor, for drawing pixels near texture and edges."""
    x = images.float() / 255.0
    gx = torch.zeros_like(x)
    gy = torch.zeros_like(x)
    gx[:, :, 1:-1] = (x[:, :, 2:] - x[:, :, :-2]) / 2
    gy[:, 1:-1] = (x[:, 2:] - x[:, :-2]) / 2
    mag = (gx.abs() + gy.abs()).sum(-1).reshape(-1)
    mag = mag + 0.05 * mag.mean()
    return torch.cumsum(mag.double(), 0)


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
    torch.manual_seed(cfg.seed)
    g = torch.Generator(device="cpu").manual_seed(cfg.seed)
    dev = torch.device(device)
    n, h, w = data.images.shape[:3]
    images = torch.from_numpy(np.ascontiguousarray(data.images)).to(dev)                       # uint8
    depths = torch.from_numpy(np.ascontiguousarray(data.depths, dtype=np.float32)).to(dev)
    depth_ok = depth_supervised(depths, cfg.depth_edge_m, cfg.far_m)
    k = torch.tensor(data.intrinsics, dtype=torch.float32, device=dev)
    c2w0 = torch.tensor(data.poses_c2w, dtype=torch.float32, device=dev)
    scene = window_scene(data.poses_c2w, data.intrinsics, (w, h), cfg.far_m)
    scene = Scene(scene.centre.to(dev), scene.scale_m, scene.lo.to(dev), scene.hi.to(dev))
    fld = build_field(cfg, scene.scale_m).to(dev)
    grid = OccupancyGrid(scene.lo, scene.hi, cfg.occupancy_res, dev)
    model = NerfModel(cfg, fld, grid, scene, c2w0.clone(), k, (w, h))
    init_occupancy(model, depths, c2w0, k)
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
    step_m = float(cfg.step_scale / k[:, 0].mean() * 0.5)
    history: list[dict] = []
    if cfg.field_kind == "permuto":  # build or load the fused kernel before the clock starts: a first build on
        load_permuto_ext(dev.type)   # a fresh machine takes over a minute of compiling, not of fitting
    t0 = time.perf_counter()
    n_samples_total = 0
    n_edge = int(round(cfg.rays_per_step * cfg.edge_ray_share))
    edge_cdf = gradient_cdf(images[train_idx]) if n_edge else None
    val_cdf = gradient_cdf(images[val_idx]) if len(val_idx) and cfg.val_register_edge_share > 0 else None
    for step in range(cfg.steps):
        frames, u, v = draw_pixels(train_idx, cfg.rays_per_step, h, w, g, edge_cdf, n_edge)
        # half the rays move the poses (colour loss only); the other half carry the depth loss, detached
        pose_rays = torch.arange(cfg.rays_per_step, device=dev) % 2 == 0
        pose_on = cfg.refine_poses and step >= cfg.pose_warmup_steps
        o, d = _rays_for(model, poses, c2w0, k, frames, u.float() + 0.5, v.float() + 0.5,
                         pose_rays if pose_on else torch.zeros_like(pose_rays))
        dgt = depths[frames, v, u]
        # behind an opaque surface nothing is visible: stop valid-depth rays a margin past the sensor depth
        t_max = torch.where(dgt > 0, dgt * 1.05 + 0.05, torch.full_like(dgt, cfg.far_m))
        if cfg.train_sampling == "depth":
            s = depth_guided(dgt, d, cfg.surface_samples, cfg.free_samples, cfg.near_m, cfg.far_m)
        else:
            s = march(o, d, edges, occ_fn, jitter=True, max_per_ray=cfg.max_samples_per_ray,
                      t_max=t_max if cfg.truncate_at_depth else None)
        if cfg.train_early_stop > 0 and cfg.train_sampling != "depth":
            s = visible_samples(model, o, d, s, cfg.train_early_stop)
        n_samples_total += len(s)
        sigma, col, _, _ = model.shade(o, d, s)
        wts, left = composite_weights(sigma, s.delta, s.ray_index, s.n_rays)
        rgb = accumulate(col, wts, s.ray_index, s.n_rays)
        target = images[frames, v, u].float() / 255.0
        loss_c = torch.mean((rgb - target) ** 2)
        loss = loss_c
        w_depth = depth_weight(cfg, step)
        if w_depth > 0:
            dpred = accumulate(s.t_mid, wts, s.ray_index, s.n_rays) + left * cfg.far_m
            m = (~pose_rays) & depth_ok[frames, v, u]
            if m.any():
                loss = loss + w_depth * torch.mean(torch.abs(dpred[m] - dgt[m]))
        if cfg.opacity_loss_weight > 0:
            # opacity reached by t_max: every sample of a valid-depth ray before it
            opa = accumulate((s.t_mid <= t_max[s.ray_index]).float(), wts, s.ray_index, s.n_rays)
            m = (~pose_rays) & (dgt > 0) & (dgt < cfg.far_m)
            if m.any():
                loss = loss + cfg.opacity_loss_weight * torch.mean(1 - opa[m])
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
                     edge_cdf=val_cdf, edge_share=cfg.val_register_edge_share)
        if step % 50 == 0 or step == cfg.steps - 1:
            rec = {"step": step, "loss": float(loss.detach()), "psnr": -10 * math.log10(max(float(loss_c.detach()), 1e-10)),
                   "occupied": grid.occupied_share(), "samples_per_ray": len(s) / cfg.rays_per_step}
            history.append(rec)
            if progress:
                progress(step + 1, cfg.steps, {"psnr": rec["psnr"]})
    if len(val_idx) and cfg.refine_poses:
        register(model, poses, val_opt, c2w0, k, images, val_idx, cfg.val_register_final_steps, g,
                 anneal=cfg.val_register_anneal, edge_cdf=val_cdf, edge_share=cfg.val_register_edge_share)
    fit_s = time.perf_counter() - t0
    with torch.no_grad():
        final = poses.apply(c2w0, torch.arange(n, device=dev)) if cfg.refine_poses else c2w0
    model.poses_c2w = final.detach().clone()
    train_psnr = float(np.mean([h_["psnr"] for h_ in history[-3:]]))
    res = FitResult(model, final.cpu().numpy().astype(np.float64), cfg.steps, fit_s, {}, train_psnr,
                    float("nan"), float("nan"), param_count(fld), history, {})
    if render_val:
        validate(res, data, model.render_image)
    return res


def validate(res: FitResult, data: WindowData, render: Callable[[int], dict]) -> None:
    """Render every validation frame with `render(i)` (a dict with at least rgb [H, W, 3] and
    samples_per_ray) and fill res.renders, val_psnr, samples_per_ray and render_s_per_image."""
    spr, render_s = [], []
    for i in np.flatnonzero(~data.is_train).tolist():
        t1 = time.perf_counter()
        out = render(i)
        render_s.append(time.perf_counter() - t1)
        res.renders[i] = out
        spr.append(out["samples_per_ray"])
        target = torch.from_numpy(data.images[i]).to(out["rgb"].device).float() / 255.0
        res.val_psnr[int(data.frame_ids[i])] = psnr(out["rgb"], target)
    res.samples_per_ray = float(np.mean(spr)) if spr else float("nan")
    res.render_s_per_image = float(np.median(render_s)) if render_s else float("nan")


@torch.no_grad()
def visible_samples(model: NerfModel, o: Tensor, d: Tensor, s: Samples, min_transmittance: float) -> Samples:
    """The samples whose transmittance T_i (exclusive, from the current density, no gradients) is at least
    `min_transmittance`: the ones a render with early termination would reach."""
    x = o.detach()[s.ray_index] + d.detach()[s.ray_index] * s.t_mid[:, None]
    sigma = model.field.density(model.scene.normalise(x))
    keep = transmittance(sigma, s.delta, s.ray_index, s.n_rays) >= min_transmittance
    return Samples(s.ray_index[keep], s.t_mid[keep], s.delta[keep], s.n_rays)


def register(model: NerfModel, poses: PoseCorrection, opt: torch.optim.Optimizer, c2w0: Tensor, k: Tensor,
             images: Tensor, val_idx: Tensor, steps: int, g: torch.Generator, rays: int = 1024,
             anneal: float = 1.0, edge_cdf: Tensor | None = None, edge_share: float = 0.0) -> None:
    """Optimise only the validation poses against the frozen model (colour loss). The learning rates fall
    exponentially to `anneal` times their value over the steps (and are restored after); an `edge_share` of
    the rays is drawn from `edge_cdf` (gradient_cdf of images[val_idx]), the rest uniformly."""
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
            wts, _ = composite_weights(sigma, s.delta, s.ray_index, s.n_rays)
            rgb = accumulate(col, wts, s.ray_index, s.n_rays)
            loss = torch.mean((rgb - images[frames, v, u].float() / 255.0) ** 2)
            opt.zero_grad(set_to_none=True)
            if torch.isfinite(loss):
                loss.backward()
                opt.step()
    finally:
        for p, r in zip(fld.parameters(), req):
            p.requires_grad_(r)
        for grp, lr in zip(opt.param_groups, lr0):
            grp["lr"] = lr


@torch.no_grad()
def init_occupancy(model: NerfModel, depths: Tensor, c2w: Tensor, k: Tensor, stride: int = 2) -> None:
    """Occupied cells from the back-projected sensor depth (with the odometry poses), plus cells along
    rays without valid depth (the sensor saw nothing there, so anything may be there)."""
    n, h, w = depths.shape
    v, u = torch.meshgrid(torch.arange(0, h, stride, device=depths.device) + 0.5,
                          torch.arange(0, w, stride, device=depths.device) + 0.5, indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    surf, free_o, free_d = [], [], []
    for i in range(n):
        dd = depths[i, v.long(), u.long()]
        o, d = pixel_rays(k[i].expand(u.shape[0], 4), c2w[i].expand(u.shape[0], 4, 4), u, v)
        ok = (dd > model.cfg.near_m) & (dd < model.cfg.far_m)
        surf.append(o[ok] + d[ok] * dd[ok, None])
        free_o.append(o[~ok])
        free_d.append(d[~ok])
    t = torch.linspace(model.cfg.near_m, model.cfg.far_m, 64, device=depths.device)
    fo, fd = torch.cat(free_o), torch.cat(free_d)
    model.grid.init_from_points(torch.cat(surf), (fo, fd, t) if len(fo) else None, dilate=model.cfg.occupancy_dilate)
