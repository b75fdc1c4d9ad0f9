"""Procedural, view-independent 3D textures: hashed lattice value noise evaluated at world points.

A texture is a function of the surface point only (never of the viewing ray), so every view of a
point sees the same albedo: what a NeRF can fit exactly and what SfM can match between frames.

Value noise: random values on the integer lattice of p / scale, blended with the smoothstep
f^2 (3 - 2 f) of the fractional part. The lattice hash is h = (ix * P1) ^ (iy * P2) ^ (iz * P3) in
uint32, mixed by a multiplication with the golden ratio constant and a shift to 16 bits, which
indexes a table of 65536 random values drawn from the seed.
Example: value_noise(p, 0.01) varies over about 1 cm; fbm(p, 0.04, 3) adds octaves of 4, 2 and 1 cm.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

_BITS = 16
_P = np.array([73856093, 19349663, 83492791], np.uint32)
_GOLD = np.uint32(2654435761)


@lru_cache(maxsize=256)
def _table(seed: int) -> np.ndarray:
    return np.random.default_rng([int(seed), 7919]).random(1 << _BITS, dtype=np.float32)


def value_noise(p: np.ndarray, scale_m: float, seed: int = 0) -> np.ndarray:
    """Smooth noise in [0, 1] with features of size `scale_m`. p [N, 3] metres -> [N] float32."""
    q = np.ascontiguousarray(np.asarray(p, np.float32).T) * np.float32(1.0 / scale_m)  # [3, N]: rows contiguous
    fl = np.floor(q)
    f = q - fl
    f = f * f * (np.float32(3) - np.float32(2) * f)
    i = fl.astype(np.int64).astype(np.uint32)  # two's complement wrap keeps negative cells distinct
    i *= _P[:, None]
    hx0, hy0, hz0 = i
    hx1, hy1, hz1 = hx0 + _P[0], hy0 + _P[1], hz0 + _P[2]
    hxy = [hx0 ^ hy0, hx1 ^ hy0, hx0 ^ hy1, hx1 ^ hy1]   # the x-y part of the hash of the 4 corners of a face
    table = _table(seed)
    shift = np.uint32(32 - _BITS)
    h = np.empty(q.shape[1], np.uint32)

    def corner(xy: np.ndarray, hz: np.ndarray) -> np.ndarray:
        np.bitwise_xor(xy, hz, out=h)
        np.multiply(h, _GOLD, out=h)
        return table.take(np.right_shift(h, shift, out=h))

    fx, fy, fz = f
    out = []
    for hz in (hz0, hz1):
        y0 = corner(hxy[0], hz)
        y0 += (corner(hxy[1], hz) - y0) * fx
        y1 = corner(hxy[2], hz)
        y1 += (corner(hxy[3], hz) - y1) * fx
        y0 += (y1 - y0) * fy
        out.append(y0)
    return out[0] + (out[1] - out[0]) * fz


def fbm(p: np.ndarray, scale_m: float, octaves: int = 3, seed: int = 0) -> np.ndarray:
    """Fractal sum of value noise (octave o has size scale_m / 2^o and weight 1/2^o), in [0, 1]."""
    total = np.zeros(len(p), np.float32)
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += np.float32(amp) * value_noise(p, scale_m / 2 ** o, seed + 17 * o)
        norm += amp
        amp *= 0.5
    return total / np.float32(norm)


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """0 below e0, 1 above e1, smooth in between (e0 > e1 flips it)."""
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)
