"""frames: one row per paired colour+depth frame of a sequence, in time order."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "frames",
    "One row per colour frame paired with a depth frame, in time order. Poses are camera-to-world in "
    "the odometry world frame (ROS REP-103: x forward, y left, z up); the camera frame is the OpenCV "
    "optical frame (x right, y down, z forward). Image paths are relative to the data root (data/).",
    col("frame_id", pa.int32(), "index of the frame in time order, from 0"),
    col("stamp_ns", pa.int64(), "colour image timestamp", "ns"),
    col("depth_stamp_ns", pa.int64(), "timestamp of the depth image paired with it", "ns"),
    col("width", pa.int32(), "image width", "px"),
    col("height", pa.int32(), "image height", "px"),
    col("fx", pa.float64(), "focal length along x", "px"),
    col("fy", pa.float64(), "focal length along y", "px"),
    col("cx", pa.float64(), "principal point x", "px"),
    col("cy", pa.float64(), "principal point y", "px"),
    col("tx", pa.float64(), "odometry camera position x (camera-to-world translation)", "m"),
    col("ty", pa.float64(), "odometry camera position y", "m"),
    col("tz", pa.float64(), "odometry camera position z", "m"),
    col("qx", pa.float64(), "odometry camera-to-world rotation quaternion x"),
    col("qy", pa.float64(), "odometry camera-to-world rotation quaternion y"),
    col("qz", pa.float64(), "odometry camera-to-world rotation quaternion z"),
    col("qw", pa.float64(), "odometry camera-to-world rotation quaternion w (scalar part)"),
    col("rgb_path", pa.string(), "8-bit RGB PNG, relative to data/"),
    col("depth_path", pa.string(), "16-bit depth PNG, 0 = invalid, relative to data/"),
    col("depth_scale_m", pa.float64(), "metres per depth PNG unit (0.001 for millimetres)", "m"),
    col("valid_depth_frac", pa.float64(), "share of pixels with finite, positive depth", "fraction"),
    col("labelled", pa.bool_(), "true where a ground-truth annotation exists for this frame"),
    col("det_semantic_path", pa.string(), "detector semantic PNG (8-bit class id, 255 = void), relative to data/; null if the frame has no detection", nullable=True),
    col("det_instance_path", pa.string(), "detector instance PNG (16-bit, 0 = stuff/none, ids per frame only), relative to data/; null if none", nullable=True),
    col("gt_semantic_path", pa.string(), "ground-truth semantic PNG, relative to data/; null where none", nullable=True),
    col("gt_instance_path", pa.string(), "ground-truth instance PNG (ids consistent over the sequence), relative to data/; null where none", nullable=True),
)
