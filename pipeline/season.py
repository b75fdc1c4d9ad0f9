"""`pag track`: a season of one row. Reads each date's finished row tables, links the fruits into tracks
(rowmap/season/) and writes the season dataset; with ground truth (synthetic seasons) also its scores.

    data/processed/_season/
        fruit_tracks/seq=<SEQ>/part-0.parquet    one row per tracked fruit and date (schemas/fruit_tracks.py)
        fruit_track_summary.parquet              one row per track
        season_dates.parquet                     one row per date: registration, continued tracks, events
        season_scores.parquet                    scores against ground truth (evaluation schema, scope 'season')
        report.html                              the season report

The folder is built beside the old one and swapped into place in one rename (as the campaign's).
"""
from __future__ import annotations

import datetime as dt
import json
import shutil
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

import schemas
from pipeline import io
from pipeline.campaign_dataset import PARTITION_COLUMN, parquet_bytes, partition_table, recording_date
from pipeline.catalog import dataset
from rowmap.season import scoring
from rowmap.season.tracks import Config, DateRows, Season, track_season

SEASON_DIR = "_season"
"""Default folder name under data/processed/ of the season dataset (names starting with '_' are reserved)."""
_EARLIEST_STAMP_NS = 946_684_800 * 10**9


def parse_spec(spec: str) -> tuple[str, dt.date | None]:
    """'SEQ' or 'SEQ@YYYY-MM-DD' -> (seq, date or None)."""
    seq, _, date = spec.partition("@")
    if not seq:
        raise ValueError(f"--seqs item {spec!r}: expected SEQ or SEQ@YYYY-MM-DD")
    if not date:
        return seq, None
    try:
        return seq, dt.date.fromisoformat(date)
    except ValueError:
        raise ValueError(f"--seqs item {spec!r}: the date after '@' must be YYYY-MM-DD, got {date!r}") from None


def config_from(overrides: list[str]) -> Config:
    """Config from --set track.KEY=VALUE items (values read as YAML); an unknown key lists the settings."""
    names = {f.name for f in fields(Config)}
    values = {}
    for item in overrides:
        key, sep, value = item.partition("=")
        section, _, name = key.partition(".")
        if not sep or section != "track" or name not in names:
            raise ValueError(f"--set {item!r}: expected track.KEY=VALUE with KEY one of {sorted(names)}")
        values[name] = yaml.safe_load(value)
    return Config(**values)


def _read(data_root: Path, name: str, seq: str) -> pd.DataFrame:
    path = dataset(name).path(data_root, seq)
    if not path.is_file():
        raise FileNotFoundError(f"row {seq!r} has no {name} table ({path}); run `pag all --seq {seq}` first")
    return io.read_table(path, name)


def load_date(data_root: Path, seq: str, date: dt.date | None) -> tuple[DateRows, pd.DataFrame, pd.DataFrame]:
    """(the date's DateRows with day 0, its frames, its panoptic_frames); the date from SEQ@DATE, else as the
    campaign reads it (a date in the name, else the first frame stamp)."""
    fruits = _read(data_root, "fruits", seq)
    frames = _read(data_root, "frames", seq)
    pf = _read(data_root, "panoptic_frames", seq)
    if date is None:
        date, _ = recording_date(seq, int(frames.stamp_ns.min()) if len(frames) else None)
    counted = fruits[fruits.counted.astype(bool) & fruits.near_row.astype(bool)].reset_index(drop=True)
    spath = dataset("structure").path(data_root, seq)   # rows fitted before fruit_count wrote it have none
    struct = io.read_table(spath, "structure")[["x_m", "y_m", "z_m"]].to_numpy(np.float64) if spath.is_file() else None
    return DateRows(seq, date, 0.0, counted, pf[["tx", "ty", "tz"]].to_numpy(np.float64), struct), frames, pf


def set_days(rows: list[DateRows], first_stamps_ns: list[int | None]) -> None:
    """Each row's day since the earliest: from first frame stamps when all are absolute (fractional days), else
    from the dates (every row then needs one: SEQ@DATE)."""
    if all(s is not None and s >= _EARLIEST_STAMP_NS for s in first_stamps_ns):
        t0 = min(first_stamps_ns)
        for r, s in zip(rows, first_stamps_ns):
            r.day = (s - t0) / 86_400e9
        return
    missing = [r.seq for r in rows if r.date is None]
    if missing:
        raise ValueError(f"rows {missing} have no recording date (no date in the name, stamps from a relative "
                         f"clock): give one as SEQ@YYYY-MM-DD")
    d0 = min(r.date for r in rows)
    for r in rows:
        r.day = float((r.date - d0).days)


def load_gt(data_root: Path, row: DateRows, frames: pd.DataFrame, pf: pd.DataFrame) -> scoring.GtDate | None:
    """The date's ground truth (synthetic rows), or None when the row has no gt/fruits.parquet and gt/poses.parquet."""
    from nerf.geometry import pose_matrix
    from rowmap.ground_truth import gt_poses_by_frame, to_ground_truth_frame

    gt = Path(data_root) / "raw" / row.seq / "gt"
    if not (gt / "fruits.parquet").is_file() or not (gt / "poses.parquet").is_file():
        return None
    cfg_path = gt / "synth_config.yaml"
    day = float((yaml.safe_load(cfg_path.read_text()) or {}).get("day", 0.0)) if cfg_path.is_file() else 0.0
    poses = pd.read_parquet(gt / "poses.parquet")
    by_frame = gt_poses_by_frame(poses, frames)
    cols = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    both = pf[["frame_id", *cols]].merge(by_frame[["frame_id", *cols]], on="frame_id", suffixes=("_map", "_gt"))
    t_map = pose_matrix(both[[f"{c}_map" for c in cols]].to_numpy(np.float64))
    t_gt = pose_matrix(both[[f"{c}_gt" for c in cols]].to_numpy(np.float64))
    season = pd.read_parquet(gt / "season.parquet") if (gt / "season.parquet").is_file() else None
    return scoring.GtDate(day, pd.read_parquet(gt / "fruits.parquet"), season,
                          to_ground_truth_frame(row.fruits, frames, by_frame, pf), t_gt @ np.linalg.inv(t_map),
                          both.tx_gt.to_numpy(np.float64), poses.tx.to_numpy(np.float64))


def rows_pipeline_seconds(data_root: Path, seq: str) -> float:
    """Wall time of the row's stages as its manifest recorded them (s)."""
    total = 0.0
    for p in (Path(data_root) / "interim" / seq / "_manifest").glob("*.json"):
        try:
            total += float(json.loads(p.read_text()).get("seconds", 0.0))
        except (ValueError, OSError):
            continue
    return total


def track(specs: list[str], data_root: Path = Path("data"), overrides: list[str] | None = None,
          name: str = SEASON_DIR, match_max_m: float = 0.05) -> tuple[Season, dict[str, float], Path]:
    """Track the rows `specs` (SEQ or SEQ@DATE) as one season and write the season dataset; returns the season,
    its scores (empty without ground truth) and the dataset folder."""
    cfg = config_from(overrides or [])
    parsed = [parse_spec(s) for s in specs]
    seqs = [s for s, _ in parsed]
    if len(set(seqs)) != len(seqs):
        raise ValueError(f"--seqs names a row twice: {seqs}")
    if len(seqs) < 2:
        raise ValueError(f"a season needs at least two dates of the row, got {seqs}")
    loaded = [load_date(data_root, s, d) for s, d in parsed]
    rows = [r for r, _, _ in loaded]
    set_days(rows, [int(f.stamp_ns.min()) if len(f) else None for _, f, _ in loaded])
    order = np.argsort([r.day for r in rows], kind="stable")
    rows, loaded = [rows[i] for i in order], [loaded[i] for i in order]
    t0 = time.perf_counter()
    season = track_season(rows, cfg)
    seconds = time.perf_counter() - t0
    scores: dict[str, float] = {}
    gts = [load_gt(data_root, r, f, pf) for r, f, pf in loaded]
    if all(g is not None for g in gts):
        scores = scoring.score(season, rows, gts, match_max_m, cfg.edge_margin_m)
    pipeline_s = sum(rows_pipeline_seconds(data_root, r.seq) for r in rows)
    scores.update(tracking_seconds=seconds, rows_pipeline_seconds=pipeline_s,
                  tracking_cost_share=seconds / pipeline_s if pipeline_s > 0 else float("nan"))
    out = write(Path(data_root) / "processed" / name, season, scores, cfg)
    return season, scores, out


def _unit(metric: str) -> str:
    for suffix, unit in (("_m", "m"), ("_mm_per_week", "mm/week"), ("_seconds", "s"), ("_share", "fraction")):
        if metric.endswith(suffix):
            return unit
    return "fraction" if metric.endswith(("_f1", "precision", "recall", "idf1")) else ""


def _table(df: pd.DataFrame, table: str) -> bytes:
    return parquet_bytes(schemas.validate(df, table))


def write(final: Path, season: Season, scores: dict[str, float], cfg: Config) -> Path:
    """The season dataset (module docstring) at `final`, replacing the previous one in one rename."""
    from pipeline import season_report

    final.parent.mkdir(parents=True, exist_ok=True)
    staging = io.staging_dir(final)
    try:
        tracks = season.tracks
        for seq, date in zip(season.dates.seq, season.dates.date):   # every date, one with no track too
            part = tracks[tracks.seq == seq]
            body = part.drop(columns=["seq", "date"]).reset_index(drop=True)
            io.atomic_write_bytes(staging / "fruit_tracks" / f"{PARTITION_COLUMN}={seq}" / "part-0.parquet",
                                  parquet_bytes(partition_table(body, "fruit_tracks", date)))
        io.atomic_write_bytes(staging / "fruit_track_summary.parquet", _table(season.summary, "fruit_track_summary"))
        io.atomic_write_bytes(staging / "season_dates.parquet", _table(season.dates, "season_dates"))
        ev = pd.DataFrame({"scope": "season", "metric": list(scores), "value": [float(v) for v in scores.values()],
                           "unit": [_unit(m) for m in scores]})
        io.atomic_write_bytes(staging / "season_scores.parquet", _table(ev, "evaluation"))
        (staging / "track_config.yaml").write_text(yaml.safe_dump(
            {f.name: getattr(cfg, f.name) for f in fields(Config)}, sort_keys=True))
        io.atomic_write_bytes(staging / "report.html", season_report.render(season, scores).encode())
        io.swap_dir(staging, final)
    except Exception:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return final
