"""Multi-resolution hash-grid encodings: the permutohedral lattice (PermutoSDF-style) used by the
model, and a cubic (trilinear, 8-corner) grid kept for the speed comparison (`pag bench encoding`).
Each has a readable pure-torch reference and a fused C++ kernel (nerf/csrc/) that tests hold to it.
Gradients flow to the table AND to the positions (camera poses are optimised through them).

Permutohedral lattice, per level l with scale sigma_l (geometric, coarse to fine) and a fixed random
shift r_l (d = 3, elevated coordinates live on the plane x0 + x1 + x2 + x3 = 0):
1. c_i = (p_i + r_l,i) * coef_l,i with coef_l,i = 1 / (sqrt((i+1)(i+2)) sigma_l), i = 0..2
2. E0 = c0 + c1 + c2, E1 = c1 + c2 - c0, E2 = c2 - 2 c1, E3 = -3 c2   (Adams et al. 2010, without
   their sqrt(2/3)(d+1) factor, which sigma absorbs)
3. rem0_i = 4 round(E_i / 4) (nearest multiple of 4, ties to even); S = sum(rem0) / 4;
   rank_i = S + #{j: r_j > r_i} + #{j < i: r_j == r_i} with r = E - rem0; where rank_i < 0 or > 3 it
   wraps into 0..3 while rem0_i moves by +4 or -4
4. t_i = (E_i - rem0_i) / 4; b[3 - rank_i] += t_i; b[4 - rank_i] -= t_i (5 slots, from 0);
   w = (b0 + 1 + b4, b1, b2, b3): barycentric weights, >= 0, summing to 1
5. vertex k = 0..3 has key_i = rem0_i + k - 4 [rank_i > 3 - k]; only key_0..2 are hashed (the
   4 coordinates sum to 0): h = (key_0 ^ key_1 * 2654435761 ^ key_2 * 805459861) mod 2^32 & (T_l - 1),
   the XOR-of-primes hash of Instant-NGP (first factor 1: neighbours along axis 0 land in nearby
   rows); T_l, level l's rows, is a power of two so the modulo is a mask
6. feature_l = sum_k w_k table[o_l + h_k]; output [N, L * F], level-major (level 0's F features first)

The table is flat, [R, F]: level l owns rows o_l .. o_l + T_l (offsets o, R = sum T_l). Every level may
have 2^log2_capacity rows; a coarse level whose lattice vertices in the scene are far fewer gets fewer
(PermutoEncoding.size_levels, as Instant-NGP sizes its coarse levels to their dense grids): a training
step's optimiser and its zeroed table gradient then cover only rows a level can use.

4 table reads per point and level, where the cubic grid needs 8. With the ranks fixed the weights
are linear in E, so d feature / d E_i = (table[v_{3-rank_i}] - table[v_{(4-rank_i) mod 4}]) / 4,
chained through steps 2 and 1 (this is what the kernel computes for d/dx). Measured on 2-core CPUs
with cache-resident level tables (2^18 x 2 floats), the fused lattice is about 1.2-1.4x faster than
the fused cubic grid per training step, not 2x: with this hash the cubic grid's 8 corners fall on
about 4.5 distinct cache lines (neighbours along axis 0 share one) against the lattice's 4, so both
move about as many bytes; the lattice saves 4 of 8 gathers and scatters, and its arithmetic (about
11 AVX-512 instructions per point and level: quarter units, a sorting network, premultiplied
primes, see nerf/csrc/) has to stay cheaper than that.

Worked example: one level, sigma = 1, r = 0, p = 0 gives E = 0, rem0 = 0, all ranks resolve to
(0, 1, 2, 3) and w = (1, 0, 0, 0): the point sits on vertex 0, key (0, 0, 0), row h = 0.

Positions are expected in normalised scene units (about [-1, 1]^3); they are clamped to
+-2^18 * finest_scale (far beyond any scene) so the lattice coordinates stay exact in float32.
"""
from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor, nn

from nerf._ext import load_permuto_ext

Backend = Literal["auto", "torch", "fused"]
P1, P2 = 2654435761, 805459861
ELEV = (1 / math.sqrt(2), 1 / math.sqrt(6), 1 / math.sqrt(12))  # 1 / sqrt((i+1)(i+2))
MAX_LATTICE_COORD = 2.0 ** 18  # |p| is clamped to this many finest cells
LEVEL_HEADROOM = 64
"""rows per lattice vertex near the scene's surfaces that size_levels gives a level (the power of two at or above,
at most the table's capacity). A fit's samples reach 4-8x the vertices the depth points touch (the space in front
of the surfaces): at 64 a coarse level's rows stay below 1/8 loaded, its hash collisions rare."""
# CPU kernels, d/dx: the forward also writes the [3, F] Jacobian of each point and level from the rows
# it reads (True: 12 F bytes per point and level, held until the backward), or the backward reads
# the rows again (False: no extra memory). Machine-dependent (2^16 points, 16 levels, T = 2^18, both
# lattices alike): True was 15-20% faster per training step on 2-core Zen 1 VMs; False is 10-25%
# faster on 2-core Sapphire Rapids VMs (2 MiB L2), where writing the Jacobian costs more than
# reading the rows again.
JACOBIAN_IN_FORWARD = False


def permuto_coefficients(scales: Tensor) -> Tensor:
    """[L] scales -> [L, 3] factors coef_l,i = 1 / (sqrt((i+1)(i+2)) sigma_l), in the scales' dtype.
    The fused kernel gets the same tensor, so both paths do bit-identical lattice arithmetic."""
    return (1.0 / scales)[:, None] * torch.tensor(ELEV, dtype=scales.dtype, device=scales.device)


def cubic_coefficients(scales: Tensor) -> Tensor:
    """[L] scales -> [L, 3] factors 1 / sigma_l (the cubic grid's cell size is sigma_l)."""
    return (1.0 / scales)[:, None].expand(-1, 3).contiguous()


def _hash(k0: Tensor, k1: Tensor, k2: Tensor, mask: int | Tensor) -> Tensor:
    """Same hash as the kernel (uint32 arithmetic); int64 here, and the low bits agree. `mask`: one for
    every level, or [L] (the keys' first dimension is the level)."""
    if isinstance(mask, Tensor):
        mask = mask.reshape(-1, *([1] * (k0.dim() - 1)))
    return (k0 ^ (k1 * P1) ^ (k2 * P2)) & mask


def simplex(x: Tensor, coef: Tensor, shift: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Enclosing simplices of x [N, 3] at L levels (coef, shift [L, 3]) -> (elevated points E
    [L, N, 4], vertex keys [L, N, 4 vertices, 4 coords] int64, barycentric weights [L, N, 4]).
    sum_k w_k key_k = E; every key sums to 0 and vertex k's coordinates are all = k (mod 4).
    Weights and E are differentiable in x; ranks and keys are piecewise constant."""
    c = (x[None] + shift[:, None]) * coef[:, None]                                # [L, N, 3]
    c0, c1, c2 = c.unbind(-1)
    e = torch.stack([c0 + c1 + c2, c1 + c2 - c0, c2 - 2 * c1, -3 * c2], -1)      # [L, N, 4]
    with torch.no_grad():
        q = torch.round(e * 0.25)  # ties to even
        rem0 = q * 4
        r = e - rem0
        earlier = torch.tril(torch.ones(4, 4, dtype=torch.bool, device=x.device), -1)  # [i, j]: j < i
        larger = (r[..., None, :] > r[..., :, None]) | ((r[..., None, :] == r[..., :, None]) & earlier)
        rank = larger.sum(-1) + q.sum(-1, keepdim=True).long()                      # [L, N, 4]
        wrap = (rank < 0).long() - (rank > 3).long()
        rank = rank + 4 * wrap
        rem0 = rem0.long() + 4 * wrap
        k = torch.arange(4, device=x.device)
        keys = rem0[..., None, :] + k[:, None] - 4 * (rank[..., None, :] > (3 - k)[:, None]).long()
    t = (e - rem0) * 0.25
    b = torch.zeros(*e.shape[:-1], 5, dtype=e.dtype, device=e.device)
    b = b.scatter_add(-1, 3 - rank, t).scatter_add(-1, 4 - rank, -t)
    w = torch.cat([(b[..., :1] + 1) + b[..., 4:], b[..., 1:4]], -1)
    return e, keys, w


def lattice(x: Tensor, coef: Tensor, shift: Tensor, mask: int | Tensor) -> tuple[Tensor, Tensor]:
    """x [N, 3], coef and shift [L, 3], mask (rows - 1, one or [L]) -> (hashed rows within each level
    [L, N, 4] int64, weights [L, N, 4])."""
    _, keys, w = simplex(x, coef, shift)
    return _hash(keys[..., 0], keys[..., 1], keys[..., 2], mask), w


def level_masks(offsets: Tensor) -> Tensor:
    """[L + 1] row offsets -> [L] hash masks (each level's rows - 1)."""
    return offsets[1:] - offsets[:-1] - 1


def _gather(table: Tensor, offsets: Tensor, rows: Tensor, w: Tensor) -> Tensor:
    """table [R, F] with offsets [L + 1], rows (within each level) / w [L, N, V] -> [N, L * F] (level-major)."""
    n_levels, n_feat = rows.shape[0], table.shape[1]
    flat = rows + offsets[:-1].to(rows.device)[:, None, None]
    v = table[flat.reshape(-1)].view(*rows.shape, n_feat)  # [L, N, V, F]
    return (v * w[..., None]).sum(2).transpose(0, 1).reshape(rows.shape[1], n_levels * n_feat)


def permuto_encode_reference(x: Tensor, table: Tensor, offsets: Tensor, scales: Tensor, shifts: Tensor) -> Tensor:
    """Pure torch: x [N, 3], table [R, F] with row offsets [L + 1], scales [L], shifts [L, 3] -> [N, L * F],
    level-major. Differentiable in x and table by autograd. No clamping here (the module clamps)."""
    rows, w = lattice(x, permuto_coefficients(scales), shifts, level_masks(offsets).to(x.device))
    return _gather(table, offsets, rows, w)


def cubic_rows(x: Tensor, coef: Tensor, shifts: Tensor, mask: int | Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The cubic grid's cells: x [N, 3] -> (hashed rows [L, N, 8], corners [8, 3], fractions [L, N, 3])."""
    q = (x[None] + shifts[:, None]) * coef[:, None]                                # [L, N, 3]
    i0 = torch.floor(q).detach()
    f = q - i0
    i0 = i0.long()
    corners = torch.tensor([[(k >> j) & 1 for j in range(3)] for k in range(8)], device=x.device)  # [8, 3]
    keys = i0[..., None, :] + corners                                              # [L, N, 8, 3]
    return _hash(keys[..., 0], keys[..., 1], keys[..., 2], mask), corners, f


def cubic_encode_reference(x: Tensor, table: Tensor, offsets: Tensor, scales: Tensor, shifts: Tensor) -> Tensor:
    """Trilinear 8-corner hash grid, pure torch, same hash and layout: x [N, 3] -> [N, L * F]."""
    rows, corners, f = cubic_rows(x, cubic_coefficients(scales), shifts, level_masks(offsets).to(x.device))
    w = torch.where(corners.bool(), f[..., None, :], 1 - f[..., None, :]).prod(-1)  # [L, N, 8]
    return _gather(table, offsets, rows, w)


class _FusedEncode(torch.autograd.Function):
    """The C++/CUDA kernels as one autograd node. When x requires grad and need_jac (see
    JACOBIAN_IN_FORWARD), the CPU forward also returns d features / d x ([L, 3 F, N], read while the
    table rows are in cache) and the backward contracts it with grad_out; otherwise (and always on
    CUDA, whose kernels return None there) the backward reads the rows again. With `bound` (the CPU
    kernels) the kernel clamps x to [-bound, bound] itself (NaN -> 0) and gives the clamped
    coordinates no gradient, as torch.nan_to_num + clamp would; without it x must be clamped already."""

    @staticmethod
    def forward(ctx, x: Tensor, table: Tensor, offsets: Tensor, coef: Tensor, shifts: Tensor, ext, kind: str,
                need_jac: bool, bound: float | None = None, known: Tensor | None = None) -> Tensor:
        ctx.extra = () if bound is None else (bound,)
        if known is not None and not need_jac:  # the features at x, from an earlier no-grad call: no forward
            out, jac = known, None
        else:
            out, jac = getattr(ext, f"{kind}_forward")(x, table, offsets, coef, shifts, need_jac, *ctx.extra)
        ctx.save_for_backward(x, table, offsets, coef, shifts)
        ctx.ext, ctx.kind, ctx.jac = ext, kind, jac
        return out

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        x, table, offsets, coef, shifts = ctx.saved_tensors
        need_x, need_table = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        g_table, g_x = getattr(ctx.ext, f"{ctx.kind}_backward")(grad_out.float().contiguous(), x, table, offsets,
                                                                coef, shifts, ctx.jac, need_table, need_x, *ctx.extra)
        ctx.jac = None
        return (g_x if need_x else None), (g_table if need_table else None), *([None] * 8)


class PermutoEncoding(nn.Module):
    """Multi-resolution permutohedral hash grid: x [N, 3] (normalised scene units, about [-1, 1]^3)
    -> features [N, n_levels * n_features], level-major.

    `coarsest_scale`/`finest_scale` are lattice spacings in the same units as x, spread
    geometrically over the levels. `backend`: "fused" (C++/CUDA kernel, error if it cannot be
    built), "torch" (the reference), "auto" (fused when available, else the reference after one
    warning). Computes in float32 whatever the input dtype or autocast state.
    """

    kind = "permuto"

    def __init__(self, n_levels: int = 16, n_features: int = 2, log2_capacity: int = 18, coarsest_scale: float = 1.0,
                 finest_scale: float = 1e-3, seed: int = 0, backend: Backend = "auto", init_std: float = 1e-4):
        super().__init__()
        if n_levels < 1 or n_features < 1:
            raise ValueError(f"n_levels and n_features must be >= 1, got {n_levels}, {n_features}")
        if not 1 <= log2_capacity <= 26:
            raise ValueError(f"log2_capacity must be in 1..26, got {log2_capacity}")
        if not 0 < finest_scale <= coarsest_scale:
            raise ValueError(f"need 0 < finest_scale <= coarsest_scale, got {finest_scale}, {coarsest_scale}")
        if backend not in ("auto", "torch", "fused"):
            raise ValueError(f"backend must be 'auto', 'torch' or 'fused', got {backend!r}")
        self.n_levels, self.n_features, self.backend = n_levels, n_features, backend
        self.capacity, self.seed, self.init_std = 2 ** log2_capacity, seed, init_std
        self.bound = MAX_LATTICE_COORD * finest_scale  # |x| clamp, scene units
        self.out_dim = n_levels * n_features
        g = torch.Generator().manual_seed(seed)
        ratio = (finest_scale / coarsest_scale) ** (1 / max(n_levels - 1, 1))
        self.register_buffer("scales", torch.tensor([coarsest_scale * ratio ** i for i in range(n_levels)],
                                                    dtype=torch.float32))
        self.register_buffer("shifts", (torch.rand(n_levels, 3, generator=g) * 10 - 5).float())  # r_l
        # [L, 3] lattice factors, derived from the scales (so not saved with them)
        self.register_buffer("coef", self.coefficients(), persistent=False)
        self.register_buffer("offsets", torch.zeros(n_levels + 1, dtype=torch.int64))  # level l: rows o_l .. o_l+1
        self.table = nn.Parameter(torch.zeros(0, n_features))
        self.set_rows([self.capacity] * n_levels)

    @property
    def rows(self) -> list[int]:
        """Each level's table rows (powers of two, at most 2^log2_capacity)."""
        return (self._offsets_cpu[1:] - self._offsets_cpu[:-1]).tolist()   # the host copy: no device sync

    def set_rows(self, rows: list[int]) -> None:
        """A new table with `rows` per level, drawn as at construction (N(0, init_std), from the seed; the
        same numbers as before per-level rows where every level has the full capacity). Only before training:
        the features learned so far are not kept."""
        if len(rows) != self.n_levels or any(r < 1 or r & (r - 1) or r > self.capacity for r in rows):
            raise ValueError(f"rows must be {self.n_levels} powers of two up to {self.capacity}, got {rows}")
        off = torch.tensor([0, *rows], dtype=torch.int64).cumsum(0)
        self.offsets.copy_(off.to(self.offsets.device))
        self._offsets_cpu = off
        g = torch.Generator().manual_seed(self.seed)
        torch.rand(self.n_levels, 3, generator=g)  # the shifts' draws come first, as at construction
        table = (torch.randn(int(off[-1]), self.n_features, generator=g) * self.init_std).float()
        self.table = nn.Parameter(table.to(self.table.device, self.table.dtype), requires_grad=self.table.requires_grad)

    def touched_rows(self, x: Tensor) -> list[int]:
        """How many distinct rows of a full-capacity table the points x [N, 3] (normalised units) touch at each
        level: about the level's lattice vertices near them (hash collisions in 2^log2_capacity rows aside).
        The lattice's rows come from the CPU kernel's own simplices where it is built (permuto_simplices, 4x
        faster than the torch reference on a window's depth points), else from the reference."""
        ext = self._kernels(torch.device("cpu")) if self.kind == "permuto" else None
        with torch.no_grad():
            x = x.float().clamp(-self.bound, self.bound).cpu().contiguous()
            out = []
            for lvl in range(self.n_levels):
                coef, shift = self.coef[lvl:lvl + 1].float().cpu(), self.shifts[lvl:lvl + 1].float().cpu()
                if ext is not None:
                    rows = ext.permuto_simplices(x, coef[0].contiguous(), shift[0].contiguous(), self.capacity)[0]
                elif self.kind == "permuto":
                    rows = lattice(x, coef, shift, self.capacity - 1)[0]
                else:
                    rows = cubic_rows(x, coef, shift, self.capacity - 1)[0]
                out.append(int(torch.unique(rows).numel()))
            return out

    def size_levels(self, x: Tensor, headroom: int = LEVEL_HEADROOM) -> list[int]:
        """Give each level the rows its vertices near the points x [N, 3] (normalised units: the scene's
        surfaces, e.g. its depth points) can use: the power of two at or above `headroom` x touched_rows, at
        most 2^log2_capacity; a new table drawn (set_rows). Without points the rows stay. Returns the rows."""
        if not len(x):
            return self.rows
        rows = [min(self.capacity, 1 << max(0, math.ceil(math.log2(max(1, headroom * n)))))
                for n in self.touched_rows(x)]
        self.set_rows(rows)
        return rows

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        """A state's table brings its own rows per level: this module takes its offsets (and size) before the
        copy. A table from before per-level rows ([L, T, F]) is read as L levels of T rows."""
        table, off = state_dict.get(prefix + "table"), state_dict.get(prefix + "offsets")
        if table is not None and table.dim() == 3:
            state_dict[prefix + "table"] = table.reshape(-1, table.shape[-1])
            off = torch.arange(table.shape[0] + 1, dtype=torch.int64) * table.shape[1]
            state_dict[prefix + "offsets"] = off
        if off is not None and off.shape == self.offsets.shape and not torch.equal(off.cpu(), self._offsets_cpu):
            self._offsets_cpu = off.cpu().clone()
            self.table = nn.Parameter(torch.empty(int(off[-1]), self.n_features, device=self.table.device,
                                                  dtype=self.table.dtype), requires_grad=self.table.requires_grad)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return (f"levels={self.n_levels}, features={self.n_features}, rows={self.rows}, "
                f"scales={float(self.scales[0]):.3g}..{float(self.scales[-1]):.3g}, backend={self.backend}")

    def _kernels(self, device: torch.device):
        if self.backend == "torch":
            return None
        ext = load_permuto_ext(device.type)
        if ext is None and self.backend == "fused":
            raise RuntimeError(f"backend='fused' asked for, but the fused kernel is unavailable on {device} "
                               f"(see the earlier warning; PAG_NO_EXT=1 also disables it); use backend='auto' or 'torch'")
        return ext

    def coefficients(self) -> Tensor:
        """[L, 3] per-level, per-axis factors applied to (x + shift)."""
        return permuto_coefficients(self.scales) if self.kind == "permuto" else cubic_coefficients(self.scales)

    def forward(self, x: Tensor, known: Tensor | None = None) -> Tensor:
        """x [N, 3] -> features [N, L * F]. `known`: the features at these very points from an earlier call
        without gradients (a training step's visibility pass): the fused kernels return them with their
        backward and skip the forward; the torch reference computes them again."""
        if x.dim() != 2 or x.shape[1] != 3:
            raise ValueError(f"expected positions [N, 3], got {tuple(x.shape)}")
        with torch.autocast(device_type=x.device.type, enabled=False):
            b = self.bound
            ext = self._kernels(x.device)
            fused = ext is not None and self.table.dtype == torch.float32
            kernel_clamps = fused and x.device.type == "cpu"  # the CPU kernel clamps while it packs the points
            x = x.float() if kernel_clamps else torch.nan_to_num(x.float(), nan=0.0, posinf=b, neginf=-b).clamp(-b, b)
            if fused:
                need_jac = JACOBIAN_IN_FORWARD and torch.is_grad_enabled() and x.requires_grad
                return _FusedEncode.apply(x.contiguous(), self.table, self._offsets_cpu, self.coef.float(),
                                          self.shifts.float(), ext, self.kind, need_jac, b if kernel_clamps else None,
                                          known)
            ref = permuto_encode_reference if self.kind == "permuto" else cubic_encode_reference
            return ref(x.to(self.table.dtype), self.table, self._offsets_cpu, self.scales.to(self.table.dtype),
                       self.shifts.to(self.table.dtype))


class CubicHashEncoding(PermutoEncoding):
    """Trilinear (8-corner) multi-resolution hash grid with the same interface and the same care in
    its kernel; here to measure what the permutohedral lattice's 4 reads buy (`pag bench encoding`)."""

    kind = "cubic"
