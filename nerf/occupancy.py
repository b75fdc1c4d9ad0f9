"""The occupancy grid: which cells of the window's bounds may contain matter.

State (the one stateful renderer object): a density EMA per cell and the occupied mask. It is
initialised from the sensor depth (cells around back-projected depth points, and every cell along rays
whose depth is invalid), then kept up to date by an explicit `update(density_fn)` call every few steps:
ema = max(decay * ema, sigma(cell point)) on the occupied cells plus a random share of the others, and
a cell stays occupied while ema * step_m > threshold (its opacity over one marching step).
"""
from __future__ import annotations

import torch
from torch import Tensor


class OccupancyGrid:
    def __init__(self, lo: Tensor, hi: Tensor, res_longest: int, device: torch.device | str = "cpu"):
        self.lo = lo.float().to(device)
        self.hi = hi.float().to(device)
        ext = self.hi - self.lo
        self.res = torch.clamp((ext / ext.max() * res_longest).ceil().long(), min=4)
        self.cell = ext / self.res
        n = int(self.res.prod())
        self.ema = torch.zeros(n, device=device)
        self.occupied = torch.ones(n, dtype=torch.bool, device=device)

    def index(self, pts: Tensor) -> tuple[Tensor, Tensor]:
        """World points [N, 3] -> flat cell index [N] and inside-bounds mask [N]."""
        ijk = torch.floor((pts - self.lo) / self.cell).long()
        inside = ((ijk >= 0) & (ijk < self.res)).all(-1)
        ijk = torch.minimum(torch.clamp(ijk, min=0), self.res - 1)
        flat = (ijk[:, 0] * self.res[1] + ijk[:, 1]) * self.res[2] + ijk[:, 2]
        return flat, inside

    def query(self, pts: Tensor) -> Tensor:
        """World points [N, 3] -> [N] bool: inside the bounds and in an occupied cell."""
        flat, inside = self.index(pts)
        return self.occupied[flat] & inside

    __call__ = query  # the grid is an occupied_fn itself (render.march then uses the fused kernel on the CPU)

    def cell_centres(self, flat: Tensor) -> Tensor:
        k = flat % self.res[2]
        j = (flat // self.res[2]) % self.res[1]
        i = flat // (self.res[1] * self.res[2])
        return self.lo + (torch.stack([i, j, k], -1).float() + 0.5) * self.cell

    def init_from_points(self, surface_pts: Tensor, free_rays: tuple[Tensor, Tensor, Tensor] | None = None,
                         dilate: int = 1, seen_empty: Tensor | None = None) -> None:
        """Occupied = cells within `dilate` cells of a surface point, plus cells along `free_rays`
        (origins, directions, t samples) where the sensor gave no depth, except the cells in `seen_empty`
        ([cells] bool, from `cells_along`): space another ray of the sensor saw through is empty."""
        occ = torch.zeros_like(self.occupied)
        chunk = 1 << 18      # points (or rays) at a time: a window's free rays x t samples would take gigabytes
        for s in range(0, surface_pts.shape[0], chunk):
            flat, inside = self.index(surface_pts[s:s + chunk])
            occ[flat[inside]] = True
        if free_rays is not None:
            free = self.cells_along(*free_rays)
            occ |= free & ~seen_empty if seen_empty is not None else free
        self.occupied = _dilate(occ, self.res, dilate) if dilate else occ
        self.ema = torch.where(self.occupied, torch.full_like(self.ema, 1e3), torch.zeros_like(self.ema))

    def cells_along(self, o: Tensor, d: Tensor, t: Tensor, chunk: int = 1 << 18) -> Tensor:
        """[cells] bool: the cells holding a point o + d t of some ray (o, d [R, 3]) at some t, where t is [S]
        (the same depths for every ray) or [R, S] (each ray its own)."""
        hit = torch.zeros_like(self.occupied)
        per_ray = t.shape[-1]
        step = max(1, chunk // max(per_ray, 1))
        for s in range(0, o.shape[0], step):
            ts = t[s:s + step] if t.dim() == 2 else t[None]
            pts = (o[s:s + step, None] + d[s:s + step, None] * ts[..., None]).reshape(-1, 3)
            f, ins = self.index(pts)
            hit[f[ins]] = True
        return hit

    @torch.no_grad()
    def update(self, density_fn, step_m: float, threshold: float, decay: float = 0.9, random_share: float = 0.01,
               chunk: int = 65536) -> None:
        """Refresh the EMA on occupied cells and a random share of the others, then re-threshold."""
        occ_idx = self.occupied.nonzero().squeeze(1)
        n = self.ema.shape[0]
        extra = torch.randint(0, n, (max(1, int(n * random_share)),), device=self.ema.device)
        idx = torch.unique(torch.cat([occ_idx, extra]))
        for s in range(0, idx.shape[0], chunk):
            part = idx[s:s + chunk]
            pts = self.cell_centres(part) + (torch.rand(part.shape[0], 3, device=part.device) - 0.5) * self.cell
            sigma = torch.nan_to_num(density_fn(pts), nan=0.0, posinf=1e6)
            self.ema[part] = torch.maximum(self.ema[part] * decay, sigma)
        self.occupied = self.ema * step_m > threshold

    def occupied_share(self) -> float:
        return float(self.occupied.float().mean())

    def state_dict(self) -> dict:
        return {"lo": self.lo, "hi": self.hi, "res": self.res, "ema": self.ema, "occupied": self.occupied}

    @classmethod
    def from_state(cls, state: dict) -> "OccupancyGrid":
        g = cls.__new__(cls)
        g.lo, g.hi, g.res, g.ema, g.occupied = (state[k] for k in ("lo", "hi", "res", "ema", "occupied"))
        g.cell = (g.hi - g.lo) / g.res
        return g


def _dilate(cells: Tensor, res: Tensor, by: int) -> Tensor:
    """[cells] bool grown by `by` cells in every direction (a 3D max filter)."""
    grid = cells.reshape(*res.tolist()).float()[None, None]
    return torch.nn.functional.max_pool3d(grid, 2 * by + 1, stride=1, padding=by).reshape(-1) > 0
