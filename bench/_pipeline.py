"""Run the whole pipeline on a synthetic variant and collect its cost and quality (shared by `pag bench scale`
and `pag bench rows`).

A variant is a sequence name (`synth_...`) plus `--set` overrides. `run_variant` runs every active stage
through the normal runner (so a rerun skips what is already done, and a stopped run resumes at the stage
it stopped in), then reads back per stage the wall time and peak memory of the process tree (the runner's
manifest records) and the scores of `evaluate` (the catalog's evaluation table).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.catalog import dataset
from pipeline.io import read_table
from pipeline.provenance import stage_costs
from pipeline.runner import Runner

QUALITY: dict[str, tuple[tuple[str, str], ...]] = {
    # column -> (scope, metric) candidates in evaluation.parquet, first present wins
    "count_gt": (("row", "count_gt"),),
    "count_pred": (("row", "count_pred"),),
    "count_error_rel": (("row", "count_error_rel"),),
    "recall": (("row", "fruit_recall"),),
    "precision": (("row", "fruit_precision"),),
    "row_id_consistency": (("row", "id_consistency"),),
    "window_id_consistency": (("windows_mean", "id_consistency"),),
    "pq": (("row", "pq"), ("windows_mean", "pq")),
    "pq_detector": (("windows_mean", "pq_detector"), ("row", "pq_detector")),
    "miou": (("row", "miou"), ("windows_mean", "miou")),
    "diameter_median_err_m": (("row", "diameter_median_abs_err_m"),),
    "psnr_db": (("windows_mean", "psnr"),),
}
"""Quality columns a variant reports (NaN where the evaluation has no such score)."""
QUALITY_DOC = {
    "count_gt": "countable ground-truth fruits of the near row (fruits",
    "count_pred": "fruits counted by the pipeline (fruits)",
    "count_error_rel": "(count_pred - count_gt) / count_gt (fraction; negative = fruits missed)",
    "recall": "counted fruits matched to a ground-truth fruit by 3D position / count_gt (fraction)",
    "precision": "matched counted fruits / counted fruits (fraction)",
    "row_id_consistency": "row-level fruit-id consistency of the fused panoptic renders (fraction)",
    "window_id_consistency": "mean over windows of the NeRF renders' fruit-id consistency (fraction)",
    "pq": "panoptic quality of the fused row-level renders (fraction)",
    "pq_detector": "panoptic quality of the detector input on the same frames (fraction)",
    "miou": "mean IoU of the fused semantic renders (fraction)",
    "diameter_median_err_m": "median |diameter error| of matched fruits (m)",
    "psnr_db": "mean validation PSNR over windows (dB)",
}


@dataclass
class VariantRun:
    """Cost and quality of one pipeline run on a synthetic variant."""

    seq: str
    minutes: float
    """wall time of this call (stages skipped as up to date cost nothing)."""
    stages: pd.DataFrame
    """one row per stage: stage, seconds, peak_rss_mb (from the manifest, so also for stages an earlier call ran)."""
    quality: dict[str, float] = field(default_factory=dict)
    """QUALITY columns."""

    def peak_rss_mb(self) -> float:
        return float(self.stages.peak_rss_mb.max()) if len(self.stages) else float("nan")

    def stage_minutes(self) -> float:
        return float(self.stages.seconds.sum()) / 60 if len(self.stages) else float("nan")


def settings(values: dict[str, object]) -> list[str]:
    """{'synth.n_frames': 60} -> ['synth.n_frames=60'] (runner overrides)."""
    return [f"{k}={v}" for k, v in values.items()]


def quality(data_root: Path, seq: str,
            columns: dict[str, tuple[tuple[str, str], ...]] = QUALITY) -> dict[str, float]:
    """`columns` (QUALITY by default: column -> (scope, metric) candidates) from the sequence's evaluation
    table (NaN where it has no such score, all NaN if there is none)."""
    path = dataset("evaluation").path(data_root, seq)
    ev = read_table(path, "evaluation") if path.is_file() else pd.DataFrame(columns=["scope", "metric", "value"])
    lookup = {(s, m): v for s, m, v in zip(ev.scope, ev.metric, ev.value)}
    out = {}
    for col, candidates in columns.items():
        value = next((lookup[c] for c in candidates if c in lookup), None)
        out[col] = float(value) if value is not None and np.isfinite(value) else float("nan")
    return out


def run_variant(seq: str, overrides: list[str], data_root: Path = Path("data"), force: bool = False,
                show_progress: bool = False) -> VariantRun:
    """Every active stage of `seq` with `overrides`, then its cost and quality."""
    if not seq.startswith("synth"):
        raise ValueError(f"benchmark variants are synthetic rows; their names start with 'synth', got {seq!r}")
    runner = Runner(seq, data_root=data_root, overrides=overrides, show_progress=show_progress)
    t0 = time.perf_counter()
    runner.run(force=force)
    minutes = (time.perf_counter() - t0) / 60
    names = [s.name for s in runner.active()]
    return VariantRun(seq, minutes, stage_costs(data_root, seq, names), quality(data_root, seq))


def growth_exponent(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of log y against log x: y ~ x^k gives k (1 = linear). NaN with fewer than two
    distinct positive points. Example: x = [60, 120, 240], y = [2, 4, 8] -> 1.0."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    ok = (x > 0) & (y > 0) & np.isfinite(x) & np.isfinite(y)
    if len(np.unique(x[ok])) < 2:
        return float("nan")
    return float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0])


TINY: dict[str, object] = {
    "synth.width": 64, "synth.height": 40, "synth.supersample": 1, "synth.workers": 1, "synth.write_bag": False,
    "windows.half_width": 3, "nerf_fit.model.steps": 20, "nerf_fit.model.rays_per_step": 128,
    "nerf_fit.model.n_levels": 4, "nerf_fit.model.log2_capacity": 12, "nerf_fit.panoptic.steps": 20,
    "nerf_fit.panoptic.rays_per_frame": 64, "nerf_fit.panoptic.frames_per_step": 2,
}
"""Settings of the `--quick` smoke runs: tiny images and few training steps (the numbers mean nothing; the
runs show that the harness works end to end in about a minute per variant)."""
