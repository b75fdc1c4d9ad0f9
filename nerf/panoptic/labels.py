"""The detector's per-frame panoptic input of a window (WindowLabels), aligned with its WindowData frames."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

VOID = 255
"""semantic id of a pixel without a label."""


@dataclass
class WindowLabels:
    """The detector's per-frame panoptic input of a window, aligned with WindowData's frames."""

    semantic: np.ndarray
    """[N, H, W] uint8 class id, 255 = void (no detection, or a segment the depth filter dropped)."""
    instance: np.ndarray
    """[N, H, W] int32 per-frame segment id (0 = stuff / none); ids mean nothing across frames."""
    confidence: np.ndarray
    """[N, H, W] float32 detector confidence of the pixel's segment (1 for stuff, 0 for void)."""

    def __post_init__(self) -> None:
        if not (self.semantic.shape == self.instance.shape == self.confidence.shape):
            raise ValueError(f"WindowLabels shapes differ: semantic {self.semantic.shape}, instance "
                             f"{self.instance.shape}, confidence {self.confidence.shape}")
        conf = np.asarray(self.confidence)
        if conf.dtype == np.float32 and conf.size and 0 <= conf.min() and conf.max() <= 1:  # no NaN gets past min/max
            return  # clean already: kept as given, not copied (a 1280x720 window's is hundreds of MB)
        conf = np.array(conf, np.float32)  # one copy, cleaned in place (the caller's array is kept)
        np.nan_to_num(conf, copy=False, nan=0.0, posinf=1.0, neginf=0.0)
        self.confidence = np.clip(conf, 0, 1, out=conf)

    def take(self, idx: np.ndarray) -> "WindowLabels":
        """The labels of the frames `idx` only, in that order."""
        return WindowLabels(self.semantic[idx], self.instance[idx], self.confidence[idx])
