"""The catalog: every dataset the DAG passes between stages, where it lives and what it is.

Stages never open data/ paths themselves; the runner loads each declared input from here and
writes each declared output here (tables atomically, directories by an atomic swap).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal


@dataclass(frozen=True)
class Dataset:
    name: str
    kind: Literal["table", "dir"]
    area: Literal["raw", "interim", "processed"]
    relpath: str
    """Path inside data/<area>/<SEQ>/ ('' = the whole folder)."""
    doc: str
    schema: str = ""
    """Schema name in schemas/ for tables ('' = the dataset's own name)."""

    def path(self, data_root: Path, seq: str) -> Path:
        base = data_root / self.area / seq
        return base / self.relpath if self.relpath else base


def _t(name: str, area: str, doc: str, schema: str = "") -> Dataset:
    return Dataset(name, "table", area, f"{name}.parquet", doc, schema or name)  # type: ignore[arg-type]


DATASETS: dict[str, Dataset] = {
    d.name: d
    for d in (
        Dataset("raw", "dir", "raw", "", "the recorded (or synthetic) row: bag and/or PNG folder, detector output, gt/"),
        _t("frames", "interim", "paired colour+depth frames with odometry poses and intrinsics"),
        _t("detections", "interim", "detector segments per frame, as ingested"),
        _t("input_checks", "interim", "what ingest skipped, repaired or found missing: counts and notes"),
        Dataset("images", "dir", "interim", "images", "extracted rgb/ and depth/ PNGs of every frame"),
        _t("detections_filtered", "interim", "detector segments with the depth filter's verdict", "detections"),
        _t("gt_segments", "interim", "ground-truth segments with the depth filter's verdict"),
        _t("windows", "interim", "window membership and train/val split"),
        _t("colmap_poses", "interim", "COLMAP poses aligned to odometry (optional stage)"),
        _t("window_poses", "processed", "refined camera poses per window"),
        _t("window_metrics", "processed", "per-window quality and cost"),
        Dataset("nerf", "dir", "processed", "nerf", "per-window checkpoints and renders"),
        _t("renders", "processed", "every render file of the fitted windows: window, frame, kind, path"),
        _t("panoptic_frames", "processed", "fused per-frame panoptic renders"),
        Dataset("panoptic", "dir", "processed", "panoptic", "fused panoptic PNGs with row-level fruit ids"),
        _t("fruit_slots", "processed", "window instance slots mapped to row-level fruit ids"),
        _t("fruits", "processed", "one row per fruit of the row"),
        _t("counts", "processed", "fruit counts per class"),
        Dataset("fruit_map", "dir", "processed", "fruit_map", "fruit point cloud PLY"),
        _t("structure", "processed", "the row's static surfaces (stems, leaves, floor) as a voxel cloud"),
        _t("evaluation", "processed", "scores against ground truth"),
        Dataset("report", "dir", "processed", "report", "report.html and figures"),
    )
}


def dataset(name: str) -> Dataset:
    if name not in DATASETS:
        raise KeyError(f"dataset {name!r} is not in the catalog; datasets: {sorted(DATASETS)}")
    return DATASETS[name]
