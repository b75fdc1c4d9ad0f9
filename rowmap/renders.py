"""The render contract between nerf_fit and the stages after it.

A fitted window renders its validation frames: colour, depth and (with the panoptic phase) semantic and
instance images and the fruit probability. nerf_fit writes them into its `nerf` folder, named by `file_name`,
encoded by `encode`, and lists every file it wrote in the `renders` table (window_id, frame_id, kind, path;
schemas/renders.py). Readers look paths up in that table (`Renders`) and decode them with `Renders.read`;
nobody rebuilds a path.

Encodings (PNG): rgb 8-bit colour; depth 16-bit millimetres (0 = no depth, clipped at 65.535 m);
semantic 8-bit class id (255 = void); instance 16-bit window-local slot id (0 = stuff or none); fruit 8-bit
probability of the thing classes x 255 (before the post-processing that makes semantic and instance).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.images import ImageError, read_label, read_rgb, write_png

KINDS = ("rgb", "depth", "semantic", "instance", "fruit")
PANOPTIC_KINDS = ("semantic", "instance", "depth")
"""what a panoptic reader (fusion) needs of a frame."""
DEPTH_SCALE_M = 0.001
"""metres per unit of a depth render (16-bit millimetres)."""


def file_name(window_id: int, kind: str, frame_id: int) -> str:
    """Where a render lies inside the nerf folder: window_NNN/renders/<kind>_<frame, 6 digits>.png."""
    if kind not in KINDS:
        raise ValueError(f"unknown render kind {kind!r}; kinds: {list(KINDS)}")
    return f"window_{int(window_id):03d}/renders/{kind}_{int(frame_id):06d}.png"


def encode(kind: str, image) -> np.ndarray:
    """The stored array of one render: rgb float [H, W, 3] in [0, 1] -> uint8; depth float [H, W] metres ->
    uint16 mm; semantic -> uint8; instance -> uint16; fruit float [H, W] in [0, 1] -> uint8 x 255 (rgb and fruit
    given as uint8 are kept as they are). Accepts numpy arrays or (CPU or GPU) torch tensors."""
    a = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    if kind in ("rgb", "fruit"):
        return a if a.dtype == np.uint8 else (np.clip(a, 0, 1) * 255).round().astype(np.uint8)
    if kind == "depth":
        return np.clip(a * 1000, 0, 65535).round().astype(np.uint16)
    if kind == "semantic":
        return a.astype(np.uint8)
    if kind == "instance":
        return a.astype(np.uint16)
    raise ValueError(f"unknown render kind {kind!r}; kinds: {list(KINDS)}")


def write_frame(nerf_dir: Path, window_id: int, frame_id: int, images: dict) -> list[dict]:
    """Write the renders of one frame (kind -> image, any of KINDS) under `nerf_dir`; returns one row per file
    (window_id, frame_id, kind, file) with `file` relative to `nerf_dir`."""
    rows = []
    for kind in KINDS:
        if kind in images:
            name = file_name(window_id, kind, frame_id)
            write_png(Path(nerf_dir) / name, encode(kind, images[kind]))
            rows.append({"window_id": int(window_id), "frame_id": int(frame_id), "kind": kind, "file": name})
    return rows


class Renders:
    """The renders table, looked up by (window, frame, kind); paths in it are relative to `data_root`."""

    def __init__(self, table: pd.DataFrame, data_root: Path):
        self.data_root = Path(data_root)
        self._paths = {(int(w), int(f), str(k)): str(p)
                       for w, f, k, p in zip(table.window_id, table.frame_id, table.kind, table.path)}

    def relpath(self, window_id: int, frame_id: int, kind: str) -> str | None:
        """The table's path (relative to data/) of a render, or None when the window did not render it."""
        return self._paths.get((int(window_id), int(frame_id), kind))

    def has(self, window_id: int, frame_id: int, *kinds: str) -> bool:
        return all((int(window_id), int(frame_id), k) in self._paths for k in kinds)

    def frames(self, window_id: int, kind: str) -> set[int]:
        """Frames of a window with a render of `kind`."""
        return {f for (w, f, k) in self._paths if w == int(window_id) and k == kind}

    def read(self, window_id: int, frame_id: int, kind: str, shape: tuple[int, int] | None = None) -> np.ndarray:
        """A decoded render: rgb uint8 [H, W, 3], depth float32 metres [H, W], semantic and instance ids [H, W],
        fruit float32 probability [H, W].
        `shape` (height, width) is checked when given."""
        rel = self.relpath(window_id, frame_id, kind)
        if rel is None:
            have = sorted(k for (w, f, k) in self._paths if (w, f) == (int(window_id), int(frame_id)))
            raise ImageError(f"window {window_id}, frame {frame_id}: no {kind} render in renders.parquet "
                             f"(kinds listed for this frame: {have or 'none'})")
        path = self.data_root / rel
        what = f"window {window_id} {kind} render"
        if kind == "rgb":
            img = read_rgb(path)
        elif kind == "depth":
            img = read_label(path, what).astype(np.float32) * np.float32(DEPTH_SCALE_M)
        elif kind == "fruit":
            img = read_label(path, what).astype(np.float32) / np.float32(255)
        else:
            img = read_label(path, what)
        if shape is not None and img.shape[:2] != tuple(shape):
            raise ImageError(f"window {window_id}, frame {frame_id}: {kind} render {rel} is "
                             f"{img.shape[1]}x{img.shape[0]}, frames.parquet says {shape[1]}x{shape[0]}")
        return img


def read_depth(path: Path, what: str = "depth render") -> np.ndarray:
    """A depth render file as float32 metres [H, W] (0 = no depth)."""
    return read_label(path, what).astype(np.float32) * np.float32(DEPTH_SCALE_M)
