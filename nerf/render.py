"""Rays, cone marching through the occupancy grid, and compositing of packed samples.

Rays use camera-frame directions with z = 1, so the ray parameter t IS the z-depth of a sample and
rendered depth compares directly with the sensor's depth image.

Compositing (packed samples, ray_index sorted): tau_i = sigma_i * delta_i,
    T_i = exp(-sum_{j < i, same ray} tau_j)   (an EXCLUSIVE cumulative sum, never a cumprod)
The sum runs over each ray's own samples (a [rays, max samples per ray] layout), not as differences of
one cumulative sum over the whole batch: those lose float32 precision once earlier rays have summed
large optical depths (an opaque ray before a thin one changed the thin ray's weights by 3 %).
    w_i = T_i * (1 - exp(-tau_i)),  C = sum_i w_i c_i,  D = sum_i w_i t_i,  A = sum_i w_i
Example: one ray, sigma = (1, 2) over delta = (0.5, 0.5): tau = (0.5, 1), T = (1, e^-0.5),
w = (0.393, 0.383), opacity 0.777.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


def pixel_rays(k: Tensor, c2w: Tensor, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """k [R, 4] (fx, fy, cx, cy), c2w [R, 4, 4], pixel centres u, v [R] -> origins [R, 3], directions
    [R, 3] in the world with camera-frame z = 1 (not unit length)."""
    d_cam = torch.stack([(u - k[:, 2]) / k[:, 0], (v - k[:, 3]) / k[:, 1], torch.ones_like(u)], -1)
    d = torch.einsum("rij,rj->ri", c2w[:, :3, :3], d_cam)
    return c2w[:, :3, 3], d


def cone_steps(near: float, far: float, step_per_m: float, device: torch.device) -> Tensor:
    """Sample depths from near to far with dt = t * step_per_m (exponential spacing) -> edges [S+1];
    near == far gives no interval (rays get no samples)."""
    if not (math.isfinite(near) and math.isfinite(far) and near > 0 and far >= near):
        raise ValueError(f"need 0 < near <= far (finite, metres) for cone marching, got near={near}, far={far} "
                         f"(a zero near plane would never advance the exponential steps)")
    if not step_per_m > 0:
        raise ValueError(f"step_per_m must be > 0, got {step_per_m}")
    edges = [near]
    t = near
    while t < far:
        t = min(far, t + t * step_per_m)
        edges.append(t)
    return torch.tensor(edges, dtype=torch.float32, device=device)


@dataclass
class Samples:
    """Packed samples of a ray batch, sorted by ray then depth."""

    ray_index: Tensor  # [S] long
    t_mid: Tensor      # [S] depth of the sample
    delta: Tensor      # [S] length along the ray (z units times |d|)
    n_rays: int

    def __len__(self) -> int:
        return self.t_mid.shape[0]


def candidates(origins: Tensor, dirs: Tensor, edges: Tensor, occupied_fn, jitter: bool) -> tuple[Tensor, Tensor]:
    """Candidate depths t [R, S] between `edges` (jittered or mid-points) and whether each lies in an
    occupied cell [R, S]."""
    r = origins.shape[0]
    lo, hi = edges[:-1], edges[1:]
    u = torch.rand(r, lo.shape[0], device=origins.device) if jitter else torch.full((r, lo.shape[0]), 0.5, device=origins.device)
    t = lo + (hi - lo) * u                                                      # [R, S]
    with torch.no_grad():
        pts = origins.detach()[:, None, :] + dirs.detach()[:, None, :] * t[..., None]
        occ = occupied_fn(pts.reshape(-1, 3)).reshape(r, -1)
    return t, occ


def pack(t: Tensor, occ: Tensor, edges: Tensor, dirs: Tensor, first: int = 0, max_per_ray: int = 0,
         rows: Tensor | None = None) -> Samples:
    """Packed samples from candidates: per ray the occupied samples ranked [first, first + max_per_ray)
    (all if max_per_ray = 0), for the rays `rows` (all if None)."""
    if rows is not None:
        t, occ, dirs = t[rows], occ[rows], dirs[rows]
    if max_per_ray or first:
        rank = torch.cumsum(occ.int(), 1) - 1
        occ = occ & (rank >= first)
        if max_per_ray:
            occ = occ & (rank < first + max_per_ray)
    ray_index, col = occ.nonzero(as_tuple=True)
    return _packed(ray_index, col, t[ray_index, col], edges, dirs)


def _packed(ray_index: Tensor, col: Tensor, t: Tensor, edges: Tensor, dirs: Tensor) -> Samples:
    """Samples from the kept candidates (ray, candidate index, depth): each one's length along its ray is
    its edge interval times |d|."""
    return Samples(ray_index, t, (edges[1:] - edges[:-1])[col] * dirs.norm(dim=-1)[ray_index], dirs.shape[0])


def march(origins: Tensor, dirs: Tensor, edges: Tensor, occupied_fn, jitter: bool, max_per_ray: int = 0,
          first: int = 0, fused: bool = True) -> Samples:
    """Samples at `edges` (midpoints or jittered) kept where `occupied_fn(points)` says the cell is
    occupied; `first`/`max_per_ray` select the occupied samples ranked [first, first+max) per ray.
    origins/dirs [R, 3] -> Samples. When `occupied_fn` is an OccupancyGrid on the CPU and the fused
    kernel is built (and `fused`), the kernel does candidates() + pack() in one pass over the rays, with
    the same random draws and arithmetic: the same samples (tests/nerf/test_render.py)."""
    ext = _march_ext(origins, occupied_fn) if fused else None
    if ext is None:
        t, occ = candidates(origins, dirs, edges, occupied_fn, jitter)
        return pack(t, occ, edges, dirs, first, max_per_ray)
    r = origins.shape[0]
    u = torch.rand(r, edges.shape[0] - 1, device=origins.device) if jitter else None
    g = occupied_fn
    with torch.no_grad():
        ray_index, col, t = ext.march_occupied(
            origins.detach().float().contiguous(), dirs.detach().float().contiguous(), edges.contiguous(), u,
            g.occupied.contiguous(), g.lo.contiguous(), g.cell.float().contiguous(), g.res,
            None, first, max_per_ray)   # None: the kernel's optional per-ray depth limit, unused
    return _packed(ray_index, col, t, edges, dirs)


def round_size(first: int, round_samples: int, skip_empty: bool) -> int:
    """Occupied samples per ray of the rendering round that starts at rank `first`: 8, 16, then `round_samples`
    (most rays meet an opaque surface within their first few occupied samples); `round_samples` throughout
    without empty-space skipping, where the first samples are rarely the surface."""
    return min(round_samples, 8 << min(first // 8, 2)) if skip_empty else round_samples


class Rounds:
    """The occupied mid-point samples of a ray batch, taken in rounds (rendering with early termination):
    take(rows, first, n) = the samples ranked [first, first + n) of the rays `rows`, ray_index into rows.
    With the fused kernel each round marches its rays again (cheap); without it, the candidates are
    computed once and packed per round."""

    def __init__(self, origins: Tensor, dirs: Tensor, edges: Tensor, occupied_fn):
        self.o, self.d, self.edges, self.occupied_fn = origins, dirs, edges, occupied_fn
        self.fused = _march_ext(origins, occupied_fn) is not None
        if not self.fused:
            self.t, self.occ = candidates(origins, dirs, edges, occupied_fn, jitter=False)

    def take(self, rows: Tensor, first: int, n: int) -> Samples:
        if self.fused:
            return march(self.o[rows], self.d[rows], self.edges, self.occupied_fn, jitter=False, max_per_ray=n,
                         first=first)
        return pack(self.t, self.occ, self.edges, self.d, first=first, max_per_ray=n, rows=rows)


def _march_ext(origins: Tensor, occupied_fn):
    """The fused kernels' module when march() can use them here, else None."""
    from nerf.occupancy import OccupancyGrid

    if origins.device.type != "cpu" or not isinstance(occupied_fn, OccupancyGrid):
        return None
    return _cpu_kernels("march_occupied")


def _cpu_kernels(kernel: str):
    """The fused CPU kernels' module when it is built here and has `kernel`, else None."""
    from nerf._ext import load_permuto_ext

    ext = load_permuto_ext("cpu")
    return ext if ext is not None and hasattr(ext, kernel) else None


def ray_points(o: Tensor, d: Tensor, s: Samples, with_dirs: bool = True, fused: bool = True
               ) -> tuple[Tensor, Tensor | None]:
    """World points o + d t [S, 3] of packed samples and their rays' unit directions [S, 3] (None without
    `with_dirs`), differentiable in o and d [R, 3]. On the CPU with the fused kernels built (and `fused`), one
    pass per ray each way (nerf/csrc/ray_points_cpu.h) instead of gathers and index_put; equal to the
    reference to float rounding."""
    ext = _packed_ext(o, d) if fused else None
    if ext is None:
        x = o[s.ray_index] + d[s.ray_index] * s.t_mid[:, None]
        return x, torch.nn.functional.normalize(d[s.ray_index], dim=-1) if with_dirs else None
    x, dn = _RayPoints.apply(o.contiguous(), d.contiguous(), s.t_mid.detach().float().contiguous(),
                             s.ray_index.contiguous(), with_dirs, ext)
    return x, dn if with_dirs else None


class _RayPoints(torch.autograd.Function):
    """The fused kernel of ray_points(); no gradient to the samples' depths."""

    @staticmethod
    def forward(ctx, o, d, t, ray_index, with_dirs, ext):
        x, dn = ext.ray_points_forward(o.detach(), d.detach(), t, ray_index, with_dirs)
        ctx.ext = ext
        ctx.save_for_backward(o, d, t, ray_index)
        return x, dn

    @staticmethod
    def backward(ctx, g_x, g_dn):
        o, d, t, ray_index = ctx.saved_tensors
        g_x = torch.zeros(len(t), 3) if g_x is None else g_x.float().contiguous()
        g_dn = None if g_dn is None or g_dn.numel() == 0 else g_dn.float().contiguous()
        g_o, g_d = ctx.ext.ray_points_backward(g_x, g_dn, o.detach(), d.detach(), t, ray_index)
        return g_o, g_d, None, None, None, None


def composite(sigma: Tensor, rgb: Tensor, s: Samples, fused: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """Colour [R, 3], depth sum_i w_i t_i [R] and transmittance left [R] of packed samples with densities
    sigma [S] and colours rgb [S, 3] (composite_weights + accumulate, differentiable in sigma and rgb). On the
    CPU with the fused kernels built (and `fused`), one pass per ray forward and one backward
    (nerf/csrc/composite_cpu.h) instead of a dozen tensor ops; equal to the reference to float rounding."""
    ext = _packed_ext(sigma, rgb) if fused else None
    if ext is None:
        w, left = composite_weights(sigma, s.delta, s.ray_index, s.n_rays)
        return accumulate(rgb, w, s.ray_index, s.n_rays), accumulate(s.t_mid, w, s.ray_index, s.n_rays), left
    return _Composite.apply(sigma.contiguous(), rgb.contiguous(), s.t_mid.detach().float().contiguous(),
                            s.delta.detach().float().contiguous(), s.ray_index.contiguous(), s.n_rays, ext)


class _Composite(torch.autograd.Function):
    """The fused kernel of composite(); no gradient to the samples' depths and lengths."""

    @staticmethod
    def forward(ctx, sigma, rgb, t, delta, ray_index, n_rays, ext):
        colour, depth, left = ext.composite_forward(sigma.detach(), delta, rgb.detach(), t, ray_index, n_rays)
        ctx.ext = ext
        ctx.save_for_backward(sigma, rgb, t, delta, ray_index, colour, depth, left)
        return colour, depth, left

    @staticmethod
    def backward(ctx, g_colour, g_depth, g_left):
        sigma, rgb, t, delta, ray_index, colour, depth, left = ctx.saved_tensors
        zero = lambda g, like: torch.zeros_like(like) if g is None else g.float().contiguous()  # noqa: E731
        g_sigma, g_rgb = ctx.ext.composite_backward(zero(g_colour, colour), zero(g_depth, depth),
                                                    zero(g_left, left), sigma.detach(), delta, rgb.detach(), t,
                                                    ray_index, colour, depth, left)
        return g_sigma, g_rgb, None, None, None, None, None


def _packed_ext(a: Tensor, b: Tensor):
    """The fused kernels' module when composite() (a, b = sigma [S], rgb [S, 3]) or ray_points() (o, d [R, 3])
    can use them for these tensors (CPU, float32), else None."""
    if a.device.type != "cpu" or a.dtype != torch.float32 or b.dtype != torch.float32 or b.dim() != 2 \
            or b.shape[-1] != 3:
        return None
    return _cpu_kernels("composite_forward")


def composite_weights(sigma: Tensor, delta: Tensor, ray_index: Tensor, n_rays: int) -> tuple[Tensor, Tensor]:
    """Per-sample weights w [S] and per-ray transmittance left after the samples [R]. Packed,
    ray_index non-decreasing; exclusive cumulative sum per ray. sigma >= 0 may be huge or inf (an opaque
    sample: w = T there, 0 behind it); inf * 0 (an empty interval) counts as no optical depth."""
    tau = sigma * delta
    tau = torch.where(torch.isnan(tau), torch.zeros_like(tau), tau)
    excl = exclusive_cumsum_per_ray(tau, ray_index, n_rays)
    w = torch.exp(-excl) * (1 - torch.exp(-tau))
    total = torch.zeros(n_rays, dtype=tau.dtype, device=tau.device).index_add_(0, ray_index, tau)
    return w, torch.exp(-total)


RENDER_COLOUR_MIN_WEIGHT = 1e-4
"""A render runs the colour decoder only on samples whose compositing weight reaches this (unitless, 0-1; the
others add at most their weight to a channel). Window 2 of the bup20 row at 320x180: 25-33 % of the marched
samples, the colour within 79-81 dB PSNR of colouring every sample (one 8-bit step is 59 dB)."""


class HeavySamples:
    """A field's colour_where for a render round: sigma [S] -> the samples of `s` whose weight, times the
    transmittance ray_trans [R] their ray arrives with, is at least min_weight (default RENDER_COLOUR_MIN_WEIGHT).
    After the call, `weights` [S] (times ray_trans) and `left` [R] are composite_weights' for the caller to reuse."""

    def __init__(self, s: Samples, ray_trans: Tensor, min_weight: float | None = None):
        self.s, self.ray_trans = s, ray_trans
        self.min_weight = RENDER_COLOUR_MIN_WEIGHT if min_weight is None else min_weight
        self.weights: Tensor | None = None
        self.left: Tensor | None = None

    def __call__(self, sigma: Tensor) -> Tensor:
        s = self.s
        w, self.left = composite_weights(sigma.detach(), s.delta, s.ray_index, s.n_rays)
        self.weights = w * self.ray_trans[s.ray_index]
        return self.weights >= self.min_weight


def exclusive_cumsum_per_ray(x: Tensor, ray_index: Tensor, n_rays: int) -> Tensor:
    """sum_{j < i, same ray} x_j for packed x [S] (ray_index non-decreasing): scattered into a
    [n_rays, max samples per ray] layout, summed along each row, gathered back. Exact per ray (no
    cancellation against other rays' sums) and inf-safe (no subtraction). Example: x = (1, 2, 3) on
    rays (0, 0, 1) -> (0, 1, 0)."""
    if x.shape[0] == 0:
        return x
    counts = torch.bincount(ray_index, minlength=n_rays)
    pos = torch.arange(x.shape[0], device=x.device) - (torch.cumsum(counts, 0) - counts)[ray_index]
    width = int(counts.max()) + 1
    flat = ray_index * width + pos
    # row r holds 0, x_r0, x_r1, ...: the running sum at column k is the sum of the samples before sample k
    dense = x.new_zeros(n_rays * width).index_put((flat + 1,), x)
    return torch.cumsum(dense.view(n_rays, width), 1).view(-1)[flat]


def transmittance(sigma: Tensor, delta: Tensor, ray_index: Tensor, n_rays: int) -> Tensor:
    """Exclusive transmittance T_i = exp(-sum_{j < i, same ray} sigma_j delta_j) of packed samples [S]
    (ray_index non-decreasing). Example: sigma = (1, 2), delta = (0.5, 0.5) on one ray -> T = (1, 0.607)."""
    tau = sigma * delta
    tau = torch.where(torch.isnan(tau), torch.zeros_like(tau), tau)
    return torch.exp(-exclusive_cumsum_per_ray(tau, ray_index, n_rays))


def accumulate(values: Tensor, w: Tensor, ray_index: Tensor, n_rays: int) -> Tensor:
    """sum_i w_i v_i per ray: values [S, C] or [S] -> [R, C] or [R]."""
    if values.dim() == 1:
        return torch.zeros(n_rays, dtype=w.dtype, device=w.device).index_add_(0, ray_index, w * values)
    out = torch.zeros(n_rays, values.shape[1], dtype=w.dtype, device=w.device)
    return out.index_add_(0, ray_index, w[:, None] * values)
