"""COCO masks: run-length encoding (RLE, compressed string or uncompressed counts list) and polygons, read
and written with pycocotools.

RLE flattens a mask in column-major (Fortran) order; counts alternate zeros and ones, starting with zeros.
Example: a 2x2 mask [[0, 1], [0, 1]] -> counts [2, 2] -> compressed "22".
"""
from __future__ import annotations

import numpy as np
from pycocotools import mask as cocomask


def encode(mask: np.ndarray) -> dict:
    """Binary mask [H, W] -> {"size": [H, W], "counts": str} (compressed RLE, JSON-ready)."""
    m = np.asfortranarray(np.asarray(mask, np.uint8))
    rle = cocomask.encode(m)
    return {"size": [int(v) for v in rle["size"]], "counts": rle["counts"].decode("ascii")}


def decode(segmentation, height: int | None = None, width: int | None = None) -> np.ndarray:
    """A COCO segmentation -> bool mask [H, W].

    Accepts compressed RLE ({"size", "counts": str}), uncompressed RLE ({"size", "counts": [int, ...]})
    and polygons ([[x0, y0, x1, y1, ...], ...], which need `height` and `width`). An RLE whose size
    differs from (height, width), when they are given, is an error.
    """
    if isinstance(segmentation, dict):
        try:
            h, w = (int(v) for v in segmentation["size"])
            counts = segmentation["counts"]
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"not a COCO RLE mask (expected size [h, w] and counts): {err}") from err
        if height is not None and (h, w) != (height, width):
            raise ValueError(f"RLE mask is {h}x{w} (size [h, w]) but the image is {height}x{width}")
        if isinstance(counts, list):
            if not all(isinstance(c, int) and c >= 0 for c in counts):
                raise ValueError("RLE counts must be non-negative integers")
            if sum(counts) != h * w:
                raise ValueError(f"RLE counts sum to {sum(counts)}, expected {h}x{w} = {h * w}")
            rle = cocomask.frPyObjects({"size": [h, w], "counts": counts}, h, w)
        elif isinstance(counts, (str, bytes)):
            raw = counts.encode("ascii") if isinstance(counts, str) else counts
            try:
                m = cocomask.decode({"size": [h, w], "counts": raw})
            except ValueError as err:
                raise ValueError(f"RLE counts string does not describe a {h}x{w} mask: {err}") from err
            # pycocotools does not check that the runs cover the mask exactly (a short string leaves the
            # rest of the buffer unset): a valid string encodes back to itself
            if m.max(initial=0) > 1 or cocomask.encode(np.asfortranarray(m))["counts"] != raw:
                raise ValueError(f"RLE counts string does not describe a {h}x{w} mask (its runs do not cover "
                                 f"{h}x{w} = {h * w} pixels, or it is not in the canonical form pycocotools "
                                 f"writes)")
            return m.astype(bool)
        else:
            raise ValueError(f"RLE counts must be a string or a list of integers, got {type(counts).__name__}")
        return cocomask.decode(rle).astype(bool)
    if isinstance(segmentation, list):
        if height is None or width is None:
            raise ValueError("a polygon segmentation needs the image height and width")
        polys = [p for p in segmentation if isinstance(p, list)]
        if not polys or len(polys) != len(segmentation) or any(len(p) < 6 or len(p) % 2 for p in polys) \
                or not all(isinstance(v, (int, float)) for p in polys for v in p):
            raise ValueError("not a COCO polygon list (expected [[x0, y0, x1, y1, x2, y2, ...], ...] with at least "
                             "3 points each)")
        rles = cocomask.frPyObjects([[float(v) for v in p] for p in polys], height, width)
        return cocomask.decode(cocomask.merge(rles)).astype(bool)
    raise ValueError(f"not a COCO segmentation (expected an RLE dict or a polygon list), got "
                     f"{type(segmentation).__name__}")

