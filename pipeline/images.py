"""Reading the PNG files that tables reference (paths relative to data/), with clear errors."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


class ImageError(ValueError):
    """An image file is missing, unreadable or not of the expected kind."""


def read_png(path: Path, expect: str) -> np.ndarray:
    """Read a PNG unchanged (8/16 bit, 1 or 3 channels); `expect` names what it should be, for errors."""
    if not path.is_file():
        raise ImageError(f"{expect} {path} does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageError(f"{expect} {path} is not a readable PNG (truncated or corrupt?)")
    return img


def read_rgb(path: Path) -> np.ndarray:
    """[H, W, 3] uint8 RGB."""
    img = read_png(path, "RGB image")
    if img.ndim != 3 or img.shape[2] < 3:
        raise ImageError(f"RGB image {path}: expected 3 channels, got shape {img.shape}")
    return cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2RGB)


def read_depth_m(path: Path, scale_m: float) -> np.ndarray:
    """[H, W] float32 metres; 0 where invalid."""
    img = read_png(path, "depth image")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise ImageError(f"depth image {path}: expected a 16-bit single-channel PNG, got {img.dtype} {img.shape}")
    return img.astype(np.float32) * np.float32(scale_m)


def read_label(path: Path, kind: str) -> np.ndarray:
    """Semantic (8-bit) or instance (16-bit) PNG as int32 [H, W]."""
    img = read_png(path, f"{kind} PNG")
    if img.ndim != 2:
        raise ImageError(f"{kind} PNG {path}: expected a single channel, got shape {img.shape}")
    return img.astype(np.int32)


def write_png(path: Path, img: np.ndarray) -> None:
    """Write uint8/uint16 PNG (RGB arrays are given in RGB order)."""
    from pipeline.io import write_error

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise write_error(path, err) from err
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), img):
        path.unlink(missing_ok=True)
        raise write_error(path)
