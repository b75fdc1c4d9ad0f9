"""The detector's per-frame panoptic input of a window (WindowLabels), aligned with its WindowData frames."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

VOID = 255
"""semantic id of a pixel without a label."""


@dataclass
class WindowLabels:
    """The detector's per-frame panoptic input of a window, aligned with WindowData's frames.

    A pixel's confidence is its segment's score (`scores`), not a per-pixel image: at 1280x720 that keeps a
    frame's labels at 2.8 MB (uint8 class, int16 segment) instead of 9.2 MB with a float32 image."""

    semantic: np.ndarray
    """[N, H, W] uint8 class id, 255 = void (no detection, or a segment the depth filter dropped)."""
    instance: np.ndarray
    """[N, H, W] integer per-frame segment id (0 = stuff / none); ids mean nothing across frames."""
    scores: np.ndarray | None = None
    """[N, S] detector score (0-1) of frame n's segment s, for every id in `instance` (S > its largest id);
    column 0 (stuff) is 1. None: every segment scores 1. Non-finite scores count as 0."""

    def __post_init__(self) -> None:
        if self.semantic.shape != self.instance.shape or self.semantic.ndim != 3:
            raise ValueError(f"WindowLabels shapes differ or are not [N, H, W]: semantic {self.semantic.shape}, "
                             f"instance {self.instance.shape}")
        n = len(self.semantic)
        top = int(self.instance.max()) if self.instance.size else 0
        if self.instance.size and self.instance.min() < 0:
            raise ValueError("WindowLabels instance ids must be >= 0 (0 = stuff / none)")
        if self.scores is None:
            self.scores = np.ones((n, top + 1), np.float32)
            return
        scores = np.array(self.scores, np.float32)  # a small table: always a cleaned copy
        if scores.ndim != 2 or len(scores) != n or scores.shape[1] <= top:
            raise ValueError(f"WindowLabels scores are {scores.shape}: need [{n}, > {top}] (a score for every "
                             f"segment id of every frame)")
        np.nan_to_num(scores, copy=False, nan=0.0, posinf=1.0, neginf=0.0)
        self.scores = np.clip(scores, 0, 1, out=scores)
        self.scores[:, 0] = 1.0

    def confidence_at(self, frame: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        """[R] float32 confidence of pixels (frame, v, u): their segment's score, 1 for stuff, 0 for void."""
        conf = self.scores[frame, self.instance[frame, v, u]]
        conf[self.semantic[frame, v, u] == VOID] = 0.0
        return conf

    @property
    def confidence(self) -> np.ndarray:
        """[N, H, W] float32 confidence image of every frame (built on each call: for tools and tests)."""
        return self.confidence_at(*np.indices(self.semantic.shape))

    def take(self, idx: np.ndarray) -> "WindowLabels":
        """The labels of the frames `idx` only, in that order."""
        return WindowLabels(self.semantic[idx], self.instance[idx], self.scores[idx])
