"""evaluation: scores of the pipeline's outputs against ground truth."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "evaluation",
    "One row per (scope, metric). scope 'window_NNN': that window's NeRF renders (and, for *_detector, the "
    "detector PNGs) against ground truth on its validation frames; 'windows_mean': the mean over windows; "
    "'row': the fused row-level outputs (fruit counts, sizes, row-wide fruit-id consistency). Ground-truth "
    "fruits beyond the depth filter (gt_segments.kept = false) are void in every panoptic score. The unit of "
    "each metric is in the `unit` column. Empty (with a stage note) when the sequence has no ground truth.",
    col("scope", pa.string(), "'window_NNN', 'windows_mean' or 'row'"),
    col("metric", pa.string(), "metric name (psnr, pq, sq, rq, miou, pq_detector, miou_detector, id_consistency, "
        "ate_odometry_m, ate_refined_m, count_gt, count_pred, count_error_rel, diameter_mae_m, ...)"),
    col("value", pa.float64(), "metric value (null where undefined, e.g. no fruit seen in enough frames)",
        nullable=True),
    col("unit", pa.string(), "unit of value: 'dB', 'm', 'fraction', 'fruits', 'frames', ... ('' if unitless)"),
)
