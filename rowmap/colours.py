"""Colours for drawing instance ids (report panels, the fruit point cloud)."""
from __future__ import annotations

import colorsys

import numpy as np

GOLDEN_RATIO_HUE_STEP = 0.618033988749895
"""hue step between consecutive ids: consecutive ids get far-apart hues and no hue repeats exactly."""


def id_colours(ids: np.ndarray) -> np.ndarray:
    """Distinct, deterministic RGB colours [N, 3] uint8 for instance ids (golden-ratio hues, saturation 0.75,
    value 0.95). Example: id 0 -> hue 0 (red), id 1 -> hue 0.618 (blue-violet)."""
    ids = np.asarray(ids, np.int64).ravel()
    out = np.array([colorsys.hsv_to_rgb((i * GOLDEN_RATIO_HUE_STEP) % 1.0, 0.75, 0.95) for i in ids]).reshape(-1, 3)
    return (out * 255).round().astype(np.uint8)
