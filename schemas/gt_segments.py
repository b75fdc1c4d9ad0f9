"""gt_segments: ground-truth fruit segments per frame, filtered by depth like the detections."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "gt_segments",
    "One row per ground-truth thing segment per frame (where ground truth exists), with the same depth "
    "filter as the detections so evaluation ignores fruits the pipeline is told not to count.",
    col("frame_id", pa.int32(), "frame (frames.frame_id)"),
    col("instance_id", pa.int32(), "ground-truth instance id (consistent over the sequence)"),
    col("class_id", pa.int32(), "semantic class"),
    col("area_px", pa.int64(), "segment area", "px"),
    col("near_depth_frac", pa.float64(), "share of pixels with valid depth within max_depth_m", "fraction"),
    col("kept", pa.bool_(), "true if the segment survives the depth filter"),
    col("drop_reason", pa.string(), "why the segment was dropped ('' if kept)"),
)
