"""A tiny two-row synthetic campaign (rows differ by synth.seed), its config file and how to compare runs."""
from __future__ import annotations

from pathlib import Path

import pandas as pd
import yaml

SEQS = ("synth_camp_a", "synth_camp_b")
SETTINGS = {
    "synth": {"n_frames": 12, "width": 64, "height": 40, "n_labelled": 2, "supersample": 1, "workers": 1},
    "windows": {"half_width": 3},
    # one torch thread per task wherever it runs, so a local and a cluster run compute the same numbers
    "nerf_fit": {"threads_per_worker": 1,
                 "model": {"steps": 150, "rays_per_step": 128, "n_levels": 4, "log2_capacity": 12},
                 "panoptic": {"steps": 100, "rays_per_frame": 64, "frames_per_step": 2}},
    "rows": {SEQS[0]: {"synth": {"seed": 1}}, SEQS[1]: {"synth": {"seed": 2}}},
}
TIMING_COLUMNS = {"fit_s", "render_s_per_image", "panoptic_fit_s", "worker", "peak_rss_mb"}
"""window_metrics columns that depend on where and how fast a window ran, not on what it computed."""
TABLES = ("fruits", "counts", "window_metrics", "evaluation")


def write_config(path: Path) -> Path:
    path.write_text(yaml.safe_dump(SETTINGS))
    return path


def campaign_args(root: Path, config: Path, *extra: str) -> list[str]:
    return ["campaign", "--seqs", *SEQS, "--config", str(config), "--data-root", str(root), "--no-progress", *extra]


def read_partitioned(root: Path, table: str) -> pd.DataFrame:
    """A campaign table, sorted so two runs compare row by row, timing columns dropped."""
    import pyarrow.dataset as ds

    df = ds.dataset(root / "processed" / "_campaign" / table, format="parquet", partitioning="hive").to_table().to_pandas()
    df = df.drop(columns=[c for c in TIMING_COLUMNS if c in df.columns])
    df["seq"] = df["seq"].astype(str)
    keys = [c for c in ("seq", "window_id", "fruit_id", "class_id", "scope", "metric") if c in df.columns]
    return df.sort_values(keys).reset_index(drop=True)
