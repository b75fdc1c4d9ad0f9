"""campaign_rows: one row per sequence of a campaign (data/processed/_campaign/rows.parquet)."""
import pyarrow as pa

from pipeline.classes import DEFAULT_CLASSES
from schemas import col, table_schema

SCHEMA = table_schema(
    "campaign_rows",
    "One row per sequence of the last `pag campaign`: what the row yielded (fruits per class, per metre of row, "
    "size) and how good its reconstruction is (PSNR; PQ where ground truth exists). A row that failed has "
    "status 'failed', its error, and nulls where its outputs would be. The recording date is taken from the "
    "sequence name if it holds one (YYYY-MM-DD or YYYYMMDD), else from the first frame's stamp_ns read as UTC "
    "(stamps before 2000-01-01 are relative clocks: null).",
    col("seq", pa.string(), "sequence name (folder under data/raw/)"),
    col("date", pa.date32(), "recording date (see date_source); null if unknown", nullable=True),
    col("date_source", pa.string(), "where date comes from: 'name' (a date in the sequence name), 'first_stamp' "
        "(the first frame's stamp_ns as a UTC date) or '' (unknown)"),
    col("status", pa.string(), "'ok' (every stage ran or was up to date) or 'failed'"),
    col("error", pa.string(), "why the row failed ('' if ok): the stage and its message"),
    col("n_frames", pa.int32(), "frames of the row (frames.parquet)", "frames", nullable=True),
    col("row_length_m", pa.float64(), "length of the row covered: the camera's odometry path length in the "
        "horizontal plane (x, y) from the first to the last frame", "m", nullable=True),
    col("windows", pa.int32(), "NeRF windows of the row", "windows", nullable=True),
    col("windows_failed", pa.int32(), "windows whose fit failed (not fused)", "windows", nullable=True),
    col("fruits", pa.int32(), "counted fruits of the row, all classes (counts.parquet)", "fruits", nullable=True),
    *[col(f"count_{c.name}", pa.int32(), f"counted fruits of class {c.name} (id {c.id})", "fruits", nullable=True)
      for c in DEFAULT_CLASSES if c.is_thing],
    col("fruits_per_m", pa.float64(), "fruits / row_length_m", "fruits/m", nullable=True),
    col("mean_diameter_m", pa.float64(), "mean diameter_m of the counted fruits that have one", "m", nullable=True),
    col("val_psnr", pa.float64(), "mean validation PSNR over the row's fitted windows (window_metrics)", "dB",
        nullable=True),
    col("pq", pa.float64(), "panoptic quality of the fused row against ground truth (evaluation, scope 'row'); "
        "null without ground truth", "fraction", nullable=True),
    col("count_gt", pa.int32(), "ground-truth fruits the count is scored against (evaluation, scope 'row'); null "
        "without ground truth", "fruits", nullable=True),
    col("report_path", pa.string(), "the row's report.html, relative to data/ ('' if it has none)"),
)
