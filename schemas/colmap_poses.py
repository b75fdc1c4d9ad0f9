"""colmap_poses: per-window COLMAP camera poses, aligned to the odometry frame (optional stage)."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "colmap_poses",
    "One row per (window, frame) when the colmap_poses stage is enabled (empty otherwise). Each window's "
    "frames are reconstructed by COLMAP (SIFT, sequential matching, incremental mapping, fixed PINHOLE "
    "camera from frames.parquet); the reconstruction is mapped into the odometry world frame by one "
    "similarity transform (scale, rotation, translation) fitted to the registered frames' camera centres "
    "(and orientations, which fix the roll about a straight trajectory). Frames COLMAP did not register, "
    "or whose aligned position is an outlier, keep their odometry pose (source 'odometry'). Poses are "
    "camera-to-world, OpenCV camera, as in frames.parquet.",
    col("window_id", pa.int32(), "window (windows.window_id)"),
    col("frame_id", pa.int32(), "frame (frames.frame_id)"),
    col("registered", pa.bool_(), "true if COLMAP registered the frame and its aligned pose is used"),
    col("source", pa.string(), "where the pose comes from: 'colmap' (aligned COLMAP pose) or 'odometry' (fallback)"),
    col("tx", pa.float64(), "camera position x (camera-to-world translation)", "m"),
    col("ty", pa.float64(), "camera position y", "m"),
    col("tz", pa.float64(), "camera position z", "m"),
    col("qx", pa.float64(), "camera-to-world rotation quaternion x"),
    col("qy", pa.float64(), "camera-to-world rotation quaternion y"),
    col("qz", pa.float64(), "camera-to-world rotation quaternion z"),
    col("qw", pa.float64(), "camera-to-world rotation quaternion w (scalar part)"),
    col("residual_m", pa.float64(), "distance between the aligned COLMAP camera centre and the odometry one; "
        "null where COLMAP gave no pose", "m", nullable=True),
    col("rot_residual_deg", pa.float64(), "angle between the aligned COLMAP orientation and the odometry one; "
        "null where COLMAP gave no pose", "deg", nullable=True),
    col("window_rmse_m", pa.float64(), "RMS position residual of the window's alignment over the frames used; "
        "null where the window could not be aligned", "m", nullable=True),
    col("scale", pa.float64(), "metres per COLMAP unit of the window's similarity transform; null where the "
        "window could not be aligned", "m", nullable=True),
)
