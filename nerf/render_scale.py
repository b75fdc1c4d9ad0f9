"""Renders at a working scale: a fitted model seen through a camera with fewer pixels (scaled_model), its renders
resized back to the recorded size (to_full_size), and a render function that does both (render_at). The
automatic scale keeps renders at most RENDER_WIDTH pixels wide."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

RENDER_WIDTH = 320
"""Width (pixels) of the working renders with render_scale = 0 (automatic)."""


def working_scale(render_scale: float, width: int) -> float:
    """The render scale for images `width` pixels wide: render_scale, or with 0 the automatic one (the largest
    scale whose renders are at most RENDER_WIDTH wide). Example: working_scale(0, 1280) = 0.25."""
    return render_scale if render_scale > 0 else min(1.0, RENDER_WIDTH / width)


def scaled_model(model, scale: float):
    """The same model seen through a camera with `scale` times the pixels per side: the image size rounded,
    the intrinsics (fx, fy, cx, cy) scaled by the exact size ratio (pixel centres stay at half-integers, so
    continuous image coordinates simply scale). Shares the field, grid and poses; nothing is copied."""
    w, h = model.wh
    ws, hs = max(1, round(w * scale)), max(1, round(h * scale))
    k = model.intrinsics.clone()
    k[:, 0::2] *= ws / w  # fx, cx
    k[:, 1::2] *= hs / h  # fy, cy
    return replace(model, intrinsics=k, wh=(ws, hs))


def to_full_size(out: dict, wh: tuple[int, int]) -> dict:
    """A render made at a working scale, resized to the image size wh = (W, H): rgb and fruit probability
    bilinear; depth, opacity and labels nearest-neighbour. Tensors stay tensors, arrays stay arrays."""
    import cv2
    import torch

    w, h = wh

    def resize(a, linear: bool):
        is_tensor = isinstance(a, torch.Tensor)
        arr = a.detach().cpu().numpy() if is_tensor else np.asarray(a)
        # cv2 resizes uint8, uint16 and float32; other types (int32 slot ids) go through float32, exact below 2^24
        src = arr if arr.dtype in (np.uint8, np.uint16, np.float32) else arr.astype(np.float32)
        r = cv2.resize(src, (w, h), interpolation=cv2.INTER_LINEAR if linear else cv2.INTER_NEAREST).astype(arr.dtype)
        return torch.from_numpy(r).to(a.device) if is_tensor else r

    res = dict(out)
    for key in ("rgb", "depth", "opacity", "semantic", "instance", "fruit"):
        if key in out:
            res[key] = resize(out[key], key in ("rgb", "fruit"))
    return res


def render_at(render, model, scale: float):
    """render(model, i) -> a render of frame i at the working `scale`, returned at full size; a resized one keeps
    its colour at the working scale as "rgb_working"."""
    if scale >= 1:
        return lambda i: render(model, i)
    small = scaled_model(model, scale)

    def at_scale(i: int) -> dict:
        out = render(small, i)
        return {**to_full_size(out, model.wh), "rgb_working": out["rgb"]}

    return at_scale
