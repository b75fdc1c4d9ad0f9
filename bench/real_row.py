"""A row of a real recording's size end to end: cost per stage and quality.

    pag bench real_row [--seq synth_bup20] [--set KEY=VALUE ...] [--force] [--data-root data] [--out data/bench]

Runs every stage of the synthetic row `synth.preset=bup20` (1280x720 at 15 fps and 0.2 m/s, 450 frames =
6 m of row, a labelled frame every metre; see stages/synth.py) through the normal runner, so stages that
are up to date (e.g. after `make all SEQ=synth_bup20 ARGS="--set synth.preset=bup20"` with the same
settings) are not run again, then reads per stage the wall time, the peak memory of the process tree
(Dask workers included) and the commit of the run that produced the stage's outputs (the runner's
manifest records), and the quality columns of bench/_pipeline.py from the row's evaluation.

Writes <out>/real_row.parquet: one row per stage (stage, seconds, peak_rss_mb, code_version) with the row's
size, window count and quality repeated on every line. `total` sums the stages; `after_synth` leaves out the
synthesis of the recording (what a recorded row costs).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from bench._common import write_parquet
from bench._pipeline import run_variant

PRESET = "synth.preset=bup20"


def row_size(data_root: Path, seq: str) -> dict[str, int]:
    """frames, width, height and windows of the row (from its frames and windows tables)."""
    interim = Path(data_root) / "interim" / seq
    frames = pd.read_parquet(interim / "frames.parquet", columns=["width", "height"])
    windows = pd.read_parquet(interim / "windows.parquet", columns=["window_id"])
    return {"n_frames": len(frames), "width": int(frames.width.iloc[0]), "height": int(frames.height.iloc[0]),
            "n_windows": int(windows.window_id.nunique())}


def table(stages: pd.DataFrame, size: dict[str, int], quality: dict[str, float]) -> pd.DataFrame:
    """Per-stage rows plus `total` and `after_synth` (seconds summed, peak memory the largest)."""
    df = stages[["stage", "seconds", "peak_rss_mb", "code_version"]].copy()
    rest = df[df.stage != "synth"]
    sums = pd.DataFrame([
        {"stage": "total", "seconds": df.seconds.sum(), "peak_rss_mb": df.peak_rss_mb.max(), "code_version": ""},
        {"stage": "after_synth", "seconds": rest.seconds.sum(), "peak_rss_mb": rest.peak_rss_mb.max(),
         "code_version": ""}])
    df = pd.concat([df, sums], ignore_index=True)
    df["minutes"] = df.seconds / 60
    for k, v in {**size, **quality}.items():
        df[k] = v
    return df


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench real_row", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="synth_bup20", help="sequence name (must start with 'synth')")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="further settings (after synth.preset=bup20)")
    p.add_argument("--force", action="store_true", help="rerun every stage")
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    run = run_variant(a.seq, [PRESET, *a.sets], a.data_root, force=a.force, show_progress=True)
    df = table(run.stages, row_size(a.data_root, a.seq), run.quality)
    write_parquet(df, a.out / "real_row.parquet")
    print(df[["stage", "minutes", "peak_rss_mb", "code_version"]].to_string(index=False,
                                                                              float_format=lambda v: f"{v:.1f}"))
    print(pd.Series(run.quality).to_string(float_format=lambda v: f"{v:.4g}"))
    print(f"wrote {a.out / 'real_row.parquet'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
