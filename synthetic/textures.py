"""Procedural, view-independent 3D textures: value noise evaluated at world hit points."""
from __future__ import annotations

import numpy as np

_P1, _P2, _P3 = np.uint64(73856093), np.uint64(19349663), np.uint64(83492791)


def _hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    h = (ix.astype(np.int64).astype(np.uint64) * _P1) ^ (iy.astype(np.int64).astype(np.uint64) * _P2) \
        ^ (iz.astype(np.int64).astype(np.uint64) * _P3) ^ np.uint64(seed * 2654435761 % (1 << 32))
    h ^= h >> np.uint64(13)
    h *= np.uint64(0x5BD1E995)
    h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(0xFFFFFF)


def value_noise(p: np.ndarray, scale_m: float, seed: int = 0) -> np.ndarray:
    """Smooth noise in [0, 1] with features of size `scale_m`. p [N, 3] metres -> [N]."""
    q = p / scale_m
    i = np.floor(q)
    f = q - i
    f = f * f * (3 - 2 * f)
    i = i.astype(np.int64)
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1 - f[:, 0]
        for dy in (0, 1):
            wy = f[:, 1] if dy else 1 - f[:, 1]
            for dz in (0, 1):
                wz = f[:, 2] if dz else 1 - f[:, 2]
                out += wx * wy * wz * _hash01(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
    return out


def fbm(p: np.ndarray, scale_m: float, octaves: int = 3, seed: int = 0) -> np.ndarray:
    """Fractal sum of value noise, in [0, 1]."""
    total, amp, norm = np.zeros(len(p)), 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(p, scale_m / (2 ** o), seed + 17 * o)
        norm += amp
        amp *= 0.5
    return total / norm
