"""COCO run-length encoding of binary masks (the compressed "counts" string of COCO annotations).

Masks are flattened in column-major (Fortran) order; counts alternate zeros and ones, starting with
zeros. The compressed string stores each count (from the third on, as the difference to the count two
before) in 5-bit groups, least significant first, with 0x20 as the continuation flag and 48 added
to make printable characters; the last group's 0x10 bit is the sign.
Example: a 2x2 mask [[0, 1], [0, 1]] -> counts [2, 2] -> "22".
"""
from __future__ import annotations

import numpy as np


def mask_to_counts(mask: np.ndarray) -> list[int]:
    flat = np.asarray(mask, bool).ravel(order="F")
    if flat.size == 0:
        return [0]
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.concatenate([[0], change, [flat.size]])
    runs = np.diff(bounds).tolist()
    return ([0] + runs) if flat[0] else runs


def counts_to_mask(counts: list[int], height: int, width: int) -> np.ndarray:
    if sum(counts) != height * width:
        raise ValueError(f"RLE counts sum to {sum(counts)}, expected {height}x{width} = {height * width}")
    values = np.zeros(len(counts), bool)
    values[1::2] = True
    return np.repeat(values, counts).reshape((height, width), order="F")


def encode_counts(counts: list[int]) -> str:
    out = []
    for i, x in enumerate(counts):
        if i > 2:
            x -= counts[i - 2]
        more = True
        while more:
            c = x & 0x1F
            x >>= 5
            more = (x != -1) if (c & 0x10) else (x != 0)
            if more:
                c |= 0x20
            out.append(chr(c + 48))
    return "".join(out)


def decode_counts(s: str) -> list[int]:
    counts: list[int] = []
    p = 0
    while p < len(s):
        x, k, more = 0, 0, True
        while more:
            if p >= len(s):
                raise ValueError("truncated COCO RLE string")
            c = ord(s[p]) - 48
            x |= (c & 0x1F) << (5 * k)
            more = bool(c & 0x20)
            p += 1
            k += 1
            if not more and (c & 0x10):
                x |= -1 << (5 * k)
        if len(counts) > 2:
            x += counts[-2]
        counts.append(x)
    return counts


def encode(mask: np.ndarray) -> dict:
    """Binary mask [H, W] -> {"size": [H, W], "counts": str}."""
    h, w = mask.shape
    return {"size": [int(h), int(w)], "counts": encode_counts(mask_to_counts(mask))}


def decode(rle: dict) -> np.ndarray:
    """{"size": [H, W], "counts": str | list[int]} -> bool mask [H, W]."""
    try:
        h, w = (int(v) for v in rle["size"])
        counts = rle["counts"]
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"not a COCO RLE mask (expected size and counts): {err}") from err
    if isinstance(counts, str):
        counts = decode_counts(counts)
    return counts_to_mask(list(counts), h, w)
