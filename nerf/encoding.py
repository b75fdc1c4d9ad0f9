"""Multi-resolution permutohedral hash-grid encoding (PermutoSDF-style), with gradients to the table
AND to the positions, as a readable pure-torch reference and a fused C++ kernel.

Per level l with scale sigma_l (geometric, coarse to fine) and a fixed random shift r_l:
1. c_i = (p_i + r_l,i) / (sqrt((i+1)(i+2)) sigma_l), i = 0..2
2. elevate onto x0+x1+x2+x3 = 0: E0 = c0+c1+c2, E1 = c1+c2-c0, E2 = c2-2c1, E3 = -3c2
3. rem0_i = nearest multiple of 4 to E_i (ties to even); S = sum(rem0)/4; rank_i = number of larger residuals
   E_j - rem0_j (ties by index); rank += S, wrapped into 0..3 while moving rem0 by -+4
4. barycentric b (5 slots): t_i = (E_i - rem0_i)/4; b[3-rank_i] += t_i; b[4-rank_i] -= t_i;
   b0 += 1 + b4; vertex k (k = 0..3): key_i = rem0_i + k - 4 [rank_i > 3-k]
5. feature = sum_k b_k table[l, hash(key_0, key_1, key_2)], hash = (k0 ^ k1 * 2654435761 ^
   k2 * 805459861) mod T, T a power of two.
4 lookups per level (a cubic grid needs 8). With the ranks fixed the weights are linear in E, so
d feature / d E_i = (table[v_{3-rank_i}] - table[v_{(4-rank_i) mod 4}]) / 4, chained through step 1.
Example: one level, sigma = 1, r = 0, p = 0 gives E = 0, all ranks resolve to one vertex: b = (1, 0, 0, 0).
"""
from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor, nn

from nerf._ext import load_permuto_ext

Backend = Literal["auto", "torch", "fused"]
P1, P2 = 2654435761, 805459861
ELEV = (1 / math.sqrt(2), 1 / math.sqrt(6), 1 / math.sqrt(12))


def _hash(k0: Tensor, k1: Tensor, k2: Tensor, mask: int) -> Tensor:
    """Same hash as the kernel, in int64 arithmetic wrapped to uint32."""
    m32 = 0xFFFFFFFF
    return ((k0 & m32) ^ ((k1 * P1) & m32) ^ ((k2 * P2) & m32)) & mask


def lattice(x: Tensor, scale: float | Tensor, shift: Tensor, mask: int) -> tuple[Tensor, Tensor]:
    """One level: x [N, 3] -> (hashed vertex indices [N, 4] int64, barycentric weights [N, 4]).
    Weights are differentiable in x (ranks and keys are piecewise constant)."""
    inv = 1.0 / scale
    c = [(x[:, i] + shift[i]) * inv * ELEV[i] for i in range(3)]
    e = torch.stack([c[0] + c[1] + c[2], c[1] + c[2] - c[0], c[2] - 2 * c[1], -3 * c[2]], 1)  # [N, 4]
    with torch.no_grad():
        rem0 = torch.round(e * 0.25) * 4  # nearest multiple of 4, ties to even (as the kernel)
        r = e - rem0
        # rank_i = #{j: r_j > r_i} + #{j < i: r_j == r_i}
        gt = r[:, None, :] > r[:, :, None]                                      # [N, i, j]: r_j > r_i
        tie = (r[:, None, :] == r[:, :, None]) & torch.tril(torch.ones(4, 4, dtype=torch.bool, device=x.device), -1)
        rank = (gt | tie).sum(-1) + (rem0.sum(1, keepdim=True) / 4).round().long()
        lo, hi = rank < 0, rank > 3
        rank = torch.where(lo, rank + 4, torch.where(hi, rank - 4, rank))
        rem0 = torch.where(lo, rem0 + 4, torch.where(hi, rem0 - 4, rem0)).long()
    t = (e - rem0) * 0.25                                                        # [N, 4]
    b = torch.zeros(x.shape[0], 5, dtype=x.dtype, device=x.device)
    b = b.scatter_add(1, 3 - rank, t).scatter_add(1, 4 - rank, -t)
    w = torch.cat([b[:, :1] + 1 + b[:, 4:5], b[:, 1:4]], 1)
    k = torch.arange(4, device=x.device)
    keys = rem0[:, None, :3] + k[None, :, None] - 4 * (rank[:, None, :3] > (3 - k)[None, :, None]).long()  # [N, 4, 3]
    idx = _hash(keys[..., 0], keys[..., 1], keys[..., 2], mask)
    return idx, w


def permuto_encode_reference(x: Tensor, table: Tensor, scales: Tensor, shifts: Tensor) -> Tensor:
    """Pure torch: x [N, 3], table [L, T, F] -> [N, L*F] (level-major), differentiable in x and table."""
    n_levels, cap, _ = table.shape
    outs = []
    for level in range(n_levels):
        idx, w = lattice(x, scales[level], shifts[level], cap - 1)
        outs.append((table[level][idx] * w[..., None]).sum(1))
    return torch.cat(outs, 1)


def cubic_encode_reference(x: Tensor, table: Tensor, scales: Tensor, shifts: Tensor) -> Tensor:
    """Trilinear 8-corner hash grid, pure torch, same hash and layout (used for the speed comparison)."""
    n_levels, cap, _ = table.shape
    outs = []
    for level in range(n_levels):
        q = (x + shifts[level]) * (1.0 / scales[level])
        i0 = torch.floor(q).detach()
        f = q - i0
        i0 = i0.long()
        acc = 0
        for k in range(8):
            d = [(k >> j) & 1 for j in range(3)]
            w = 1
            for j in range(3):
                w = w * (f[:, j] if d[j] else 1 - f[:, j])
            idx = _hash(i0[:, 0] + d[0], i0[:, 1] + d[1], i0[:, 2] + d[2], cap - 1)
            acc = acc + table[level][idx] * w[:, None]
        outs.append(acc)
    return torch.cat(outs, 1)


class _Fused(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, table, scales, shifts, ext, kind):
        fwd = ext.permuto_forward if kind == "permuto" else ext.cubic_forward
        ctx.save_for_backward(x, table, scales, shifts)
        ctx.ext, ctx.kind = ext, kind
        return fwd(x, table, scales, shifts)

    @staticmethod
    def backward(ctx, grad_out):
        x, table, scales, shifts = ctx.saved_tensors
        bwd = ctx.ext.permuto_backward if ctx.kind == "permuto" else ctx.ext.cubic_backward
        g_table, g_x = bwd(grad_out.float().contiguous(), x, table, scales, shifts,
                           ctx.needs_input_grad[1], ctx.needs_input_grad[0])
        return (g_x if ctx.needs_input_grad[0] else None, g_table if ctx.needs_input_grad[1] else None,
                None, None, None, None)


class PermutoEncoding(nn.Module):
    """x [N, 3] (normalised scene units, about [-1, 1]^3) -> features [N, n_levels * n_features]."""

    kind = "permuto"

    def __init__(self, n_levels: int = 16, n_features: int = 2, log2_capacity: int = 18, coarsest_scale: float = 1.0,
                 finest_scale: float = 1e-3, seed: int = 0, backend: Backend = "auto", init_std: float = 1e-4):
        super().__init__()
        if n_levels < 1 or n_features < 1 or not 4 <= log2_capacity <= 26:
            raise ValueError(f"bad encoding size: levels={n_levels} features={n_features} log2_capacity={log2_capacity}")
        if not 0 < finest_scale <= coarsest_scale:
            raise ValueError(f"need 0 < finest_scale <= coarsest_scale, got {finest_scale}, {coarsest_scale}")
        self.n_levels, self.n_features, self.backend = n_levels, n_features, backend
        self.out_dim = n_levels * n_features
        g = torch.Generator().manual_seed(seed)
        ratio = (finest_scale / coarsest_scale) ** (1 / max(n_levels - 1, 1))
        self.register_buffer("scales", torch.tensor([coarsest_scale * ratio ** i for i in range(n_levels)],
                                                    dtype=torch.float32))
        self.register_buffer("shifts", (torch.rand(n_levels, 3, generator=g) * 10 - 5).float())
        table = torch.randn(n_levels, 2 ** log2_capacity, n_features, generator=g) * init_std
        self.table = nn.Parameter(table.float())

    def _ext(self, x: Tensor):
        if self.backend == "torch":
            return None
        ext = load_permuto_ext(x.device.type)
        if ext is None and self.backend == "fused":
            raise RuntimeError(f"backend='fused' asked for but the fused kernel is unavailable on {x.device}")
        return ext

    def forward(self, x: Tensor) -> Tensor:
        if x.dim() != 2 or x.shape[1] != 3:
            raise ValueError(f"expected positions [N, 3], got {tuple(x.shape)}")
        with torch.autocast(device_type=x.device.type, enabled=False):
            x = torch.nan_to_num(x.float(), nan=0.0, posinf=1e4, neginf=-1e4).clamp(-1e4, 1e4)
            ext = self._ext(x)
            if ext is not None and x.device.type == "cpu" and self.table.dtype == torch.float32:
                return _Fused.apply(x.contiguous(), self.table, self.scales, self.shifts, ext, self.kind)
            ref = permuto_encode_reference if self.kind == "permuto" else cubic_encode_reference
            return ref(x, self.table, self.scales, self.shifts)


class CubicHashEncoding(PermutoEncoding):
    """Trilinear (8-corner) multi-resolution hash grid with the same interface, for comparison."""

    kind = "cubic"
