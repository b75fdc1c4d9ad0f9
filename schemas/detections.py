"""detections: one row per detected segment per frame (the still-image detector's output)."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "detections",
    "One row per segment of the per-frame detector output. segment_id is the value of the segment's "
    "pixels in the frame's detector instance PNG; it is NOT consistent between frames. Stuff classes "
    "have no segments here (they are in the semantic PNG only). After depth_filter the kept, "
    "drop_reason and near_depth_frac columns are filled.",
    col("frame_id", pa.int32(), "frame the segment belongs to (frames.frame_id)"),
    col("segment_id", pa.int32(), "instance id of the segment in the frame's detector instance PNG (>= 1)"),
    col("class_id", pa.int32(), "semantic class of the segment"),
    col("score", pa.float64(), "detector confidence", "probability"),
    col("area_px", pa.int64(), "segment area", "px"),
    col("near_depth_frac", pa.float64(), "share of the segment's pixels with valid depth within the depth filter's max_depth_m (null before depth_filter)", "fraction", nullable=True),
    col("kept", pa.bool_(), "true if the segment survives the depth filter (true before depth_filter)"),
    col("drop_reason", pa.string(), "why the segment was dropped ('' if kept), e.g. 'depth: 12% of pixels within 1.5 m'"),
)
