"""The fusion's settings (panoptic_fusion's Config) and the names of its cost terms."""
from __future__ import annotations

from dataclasses import dataclass

TERMS = ("render", "detector", "shape", "surface", "order")
"""The terms of the per-pixel cost (assignment.terms; docs/fusion.md has their table)."""


@dataclass(frozen=True)
class Config:
    max_match_distance_m: float = 0.04
    """m, > 0: two windows' slots of one fruit lie this far apart without a shared frame, farther as masks agree."""
    min_mask_iou: float = 0.3
    """[0, 1]: how much two windows' masks of one fruit overlap on the frames both rendered."""
    group_gap_m: float = 0.03
    """m, >= 0: a slot's pixels in a frame split into groups at 3D gaps wider than this (0 = never)."""
    max_fruit_radius_m: float = 0.07
    """m, > 0: a fitted sphere wider than this is no fruit model (about 1.5 x the crop's largest radius)."""
    margin_m: float = 0.01
    """m, > 0: the depth error of a fruit model; a point this close to a fruit's surface lies on it."""
    halo_factor: float = 1.25
    """radii, >= 1: a point this far from a fruit's centre (+ margin_m) costs the fruit fully."""
    detector_split_m: float = 0.03
    """m, >= 0: a fruit's detector segments in clusters farther apart than this are two fruits (0 = never)."""
    refine_rounds: int = 1
    """rounds, 0-3: assign every frame, refit the fruit models (splits, seen surfaces), assign again."""
    terms_off: tuple[str, ...] = ()
    """names of TERMS switched off, for `pag bench fusion_terms`; () = every term on."""
    align_windows: bool = True
    """bring every window into the first window's frame through the frames they share (off: own frames)."""

    def __post_init__(self) -> None:
        ranges = {"max_match_distance_m": ("> 0", lambda v: v > 0), "max_fruit_radius_m": ("> 0", lambda v: v > 0),
                  "margin_m": ("> 0", lambda v: v > 0), "min_mask_iou": ("in [0, 1]", lambda v: 0.0 <= v <= 1.0),
                  "group_gap_m": (">= 0", lambda v: v >= 0), "detector_split_m": (">= 0", lambda v: v >= 0),
                  "halo_factor": (">= 1", lambda v: v >= 1), "refine_rounds": ("0-3", lambda v: v in range(4))}
        for name, (what, ok) in ranges.items():
            if not ok(getattr(self, name)):
                raise ValueError(f"panoptic_fusion.{name} must be {what}, got {getattr(self, name)}")
        unknown = sorted(set(self.terms_off) - set(TERMS))
        if unknown:
            raise ValueError(f"panoptic_fusion.terms_off: unknown terms {unknown}; terms: {list(TERMS)}")
