"""A fitted window's NeRF (NerfModel): the field, the occupancy grid, the scene normalisation and the
cameras, with what renders it (rays in rounds with early termination, whole images) and its checkpoint."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
from torch import Tensor

from nerf.config import NerfConfig, config_from_state
from nerf.fields import Field, build_field
from nerf.fields.base import ColourWhere
from nerf.occupancy import OccupancyGrid
from nerf.render import HeavySamples, Rounds, Samples, composite, cone_steps, pixel_rays, ray_points, round_size
from nerf.window import Scene


@dataclass
class NerfModel:
    """Everything needed to render a window again: field, occupancy grid, normalisation, poses."""

    cfg: NerfConfig
    field: Field
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
        values = dict(state["cfg"])
        if "step_scale" in values:  # checkpoints from before cone_angle: the step was step_scale pixel footprints
            values["cone_angle"] = float(values.pop("step_scale")) / float(state["intrinsics"][:, 0].mean())
        cfg = config_from_state(NerfConfig, values)
        sc = state["scene"]
        scene = Scene(sc["centre"], sc["scale_m"], sc["lo"], sc["hi"]).to(device)
        fld = build_field(cfg, scene.scale_m).to(device)
        fld.load_state_dict(state["field"])
        return cls(cfg, fld, OccupancyGrid.from_state({k: v.to(device) for k, v in state["grid"].items()}), scene,
                   state["poses_c2w"].to(device), state["intrinsics"].to(device), tuple(state["wh"]),
                   state.get("extras", {}))

    def edges(self, device) -> Tensor:
        return cone_steps(self.cfg.near_m, self.cfg.far_m, self.cfg.cone_angle, device)

    def occupied_fn(self):
        if self.cfg.skip_empty:
            return self.grid
        lo, hi = self.scene.lo, self.scene.hi
        return lambda p: ((p >= lo) & (p <= hi)).all(-1)

    def shade(self, o: Tensor, d: Tensor, s: Samples, colour: bool = True, colour_where: ColourWhere | None = None,
              grid_features: Tensor | None = None) -> tuple[Tensor, Tensor | None, Tensor, Tensor]:
        """Field at packed samples -> (sigma [S], rgb [S, 3], world points [S, 3], features [S, feature_dim]);
        colour False: rgb None, the colour decoder skipped; colour_where: only where it says (0 elsewhere);
        grid_features: the grid's features at these samples from a no-grad pass (visible_samples)."""
        x, dn = ray_points(o, d, s, with_dirs=colour)
        sigma, rgb, g = self.field(self.scene.normalise(x), dn, colour_where, grid_features)
        return sigma, rgb, x, g

    @torch.no_grad()
    def render_rays(self, o: Tensor, d: Tensor, round_samples: int = 32) -> dict[str, Tensor]:
        """Render rays in rounds of occupied samples per ray (8, 16, then `round_samples` each: most rays
        meet an opaque surface within their first few occupied samples), dropping rays whose
        transmittance fell below cfg.early_stop_transmittance (or that have no samples left). Only samples of
        weight >= RENDER_COLOUR_MIN_WEIGHT go through the colour decoder."""
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
            per_ray = round_size(first, round_samples, self.cfg.skip_empty)
            s = rounds.take(active, first, per_ray)
            first += per_ray
            if len(s) == 0:
                break
            sigma, col, _, _ = self.shade(o[active], d[active], s, colour_where=HeavySamples(s, trans[active]))
            c, dsum, left = composite(sigma, col, s)
            rgb.index_add_(0, active, c * trans[active, None])
            depth.index_add_(0, active, dsum * trans[active])
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


@torch.no_grad()
def init_occupancy(model: NerfModel, depths: Tensor, c2w: Tensor, k: Tensor, stride: int = 2,
                   carve_stride: int = 8, carve_samples: int = 192) -> None:
    """Occupied cells from the back-projected sensor depth (with the odometry poses), plus cells along
    rays without valid depth (the sensor saw nothing there, so anything may be there) except where another
    ray saw through: a cell in front of a valid depth (nearer than CARVE_SHARE of it, less one cell) on any
    ray of every `carve_stride`-th pixel is empty. A real sensor has no depth at the image border, on glare and
    beyond its range; without the carving those rays fill the room in front of every surface, and rays spend
    their samples there."""
    near, far = model.cfg.near_m, model.cfg.far_m
    surf, free_o, free_d = [], [], []
    for o, d, dd in _depth_rays(depths, c2w, k, stride):
        ok = (dd > near) & (dd < far)
        surf.append(o[ok] + d[ok] * dd[ok, None])
        free_o.append(o[~ok])
        free_d.append(d[~ok])
    fo, fd = torch.cat(free_o), torch.cat(free_d)
    free = seen_empty = None
    if len(fo):  # carve only where some ray has no depth: with depth everywhere nothing is added to carve from
        free = (fo, fd, torch.linspace(near, far, 64, device=depths.device))
        seen = [(o[ok], d[ok], dd[ok]) for o, d, dd in _depth_rays(depths, c2w, k, carve_stride)
                for ok in [(dd > near) & (dd < far)]]
        so, sd, st = (torch.cat(parts) for parts in zip(*seen))
        end = (CARVE_SHARE * st - float(model.grid.cell.max())).clamp_min(near)                   # [R]
        frac = torch.linspace(0, 1, carve_samples, device=depths.device)
        seen_empty = model.grid.cells_along(so, sd, near + (end - near)[:, None] * frac)
    model.grid.init_from_points(torch.cat(surf), free, dilate=model.cfg.occupancy_dilate, seen_empty=seen_empty)


@torch.no_grad()
def depth_points(depths: Tensor, c2w: Tensor, k: Tensor, near_m: float, far_m: float, max_points: int = 1 << 18
                 ) -> Tensor:
    """World points [P, 3] of the sensor depth of every frame (depths [N, H, W] in m, with poses and
    intrinsics) between near_m and far_m, from a pixel stride that keeps P at most about max_points."""
    n, h, w = depths.shape
    stride = max(1, math.ceil(math.sqrt(n * h * w / max_points)))
    pts = [o[ok] + d[ok] * dd[ok, None] for o, d, dd in _depth_rays(depths, c2w, k, stride)
           for ok in [(dd > near_m) & (dd < far_m)]]
    return torch.cat(pts) if pts else torch.zeros(0, 3, device=depths.device)


def _depth_rays(depths: Tensor, c2w: Tensor, k: Tensor, stride: int):
    """Per frame of depths [N, H, W] (with its pose and intrinsics): the rays of every `stride`-th pixel,
    origins and directions [R, 3], and the sensor depth [R] along them (one frame at a time, so a window's
    rays are never all in memory)."""
    n, h, w = depths.shape
    v, u = torch.meshgrid(torch.arange(0, h, stride, device=depths.device) + 0.5,
                          torch.arange(0, w, stride, device=depths.device) + 0.5, indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    for i in range(n):
        o, d = pixel_rays(k[i].expand(u.shape[0], 4), c2w[i].expand(u.shape[0], 4, 4), u, v)
        yield o, d, depths[i, v.long(), u.long()]


CARVE_SHARE = 0.9
"""init_occupancy carves the space nearer than this share of a valid depth (less one cell): the sensor's depth
noise stays well inside the last tenth of the depth."""
