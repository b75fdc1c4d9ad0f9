"""panoptic_frames: the fused per-frame panoptic renders with row-level fruit ids."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "panoptic_frames",
    "One row per frame rendered by at least one fitted window (the windows' validation frames). A frame "
    "rendered by several overlapping windows is written once, based on the window whose centre frame is nearest "
    "(smallest |offset|; ties go to the lower window_id); the fruits the other windows saw reach it "
    "through the row fruits' models (docs/fusion.md); n_windows says how many windows rendered it. In the instance PNG the id IS "
    "the row-level fruit id of fruits.parquet (0 = stuff or none).",
    col("frame_id", pa.int32(), "frame (frames.frame_id)"),
    col("stamp_ns", pa.int64(), "colour image timestamp", "ns"),
    col("window_id", pa.int32(), "window whose renders this frame's PNGs are based on (the nearest)"),
    col("offset", pa.int32(), "frame_id - the window's centre frame", "frames"),
    col("n_windows", pa.int32(), "windows that rendered this frame (> 1 where windows overlap)"),
    col("semantic_path", pa.string(), "fused semantic PNG (8-bit class id, 255 = void), relative to data/"),
    col("instance_path", pa.string(), "fused instance PNG (16-bit row-level fruit id, 0 = stuff/none), relative to data/"),
    col("rgb_path", pa.string(), "the window's NeRF colour render of this frame, relative to data/"),
    col("depth_path", pa.string(), "the window's NeRF depth render (16-bit mm), relative to data/"),
    col("n_fruits", pa.int32(), "distinct fruit ids in the frame's instance PNG"),
    col("tx", pa.float64(), "camera position x in the row frame (the window's refined pose, aligned to the "
        "first window through the frames windows share; the pose fruit_count un-projects this frame with)", "m"),
    col("ty", pa.float64(), "camera position y in the row frame", "m"),
    col("tz", pa.float64(), "camera position z in the row frame", "m"),
    col("qx", pa.float64(), "camera-to-world rotation quaternion x (row frame)"),
    col("qy", pa.float64(), "camera-to-world rotation quaternion y (row frame)"),
    col("qz", pa.float64(), "camera-to-world rotation quaternion z (row frame)"),
    col("qw", pa.float64(), "camera-to-world rotation quaternion w (row frame)"),
)
