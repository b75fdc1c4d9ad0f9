"""window_poses: the camera poses each window's NeRF ended with."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "window_poses",
    "One row per (window, frame): the camera-to-world pose used by the window's NeRF after online "
    "refinement (or the fixed input pose when refinement is off), in the world frame of frames.parquet.",
    col("window_id", pa.int32(), "window (windows.window_id)"),
    col("frame_id", pa.int32(), "frame (frames.frame_id)"),
    col("split", pa.string(), "'train' or 'val' (val poses are registered to the frozen model)"),
    col("source", pa.string(), "initial pose source: 'odometry' or 'colmap'"),
    col("refined", pa.bool_(), "true if the pose was optimised online"),
    col("tx", pa.float64(), "camera position x", "m"),
    col("ty", pa.float64(), "camera position y", "m"),
    col("tz", pa.float64(), "camera position z", "m"),
    col("qx", pa.float64(), "camera-to-world rotation quaternion x"),
    col("qy", pa.float64(), "camera-to-world rotation quaternion y"),
    col("qz", pa.float64(), "camera-to-world rotation quaternion z"),
    col("qw", pa.float64(), "camera-to-world rotation quaternion w"),
    col("delta_t_m", pa.float64(), "distance between the input pose (odometry or COLMAP, before its correction with depth) and the final camera position", "m"),
    col("delta_rot_deg", pa.float64(), "rotation angle between the initial and the final orientation", "deg"),
)
