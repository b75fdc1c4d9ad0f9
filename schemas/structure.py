"""structure: the row's static surfaces as a voxel cloud in the row frame, for registering dates (docs/season.md)."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "structure",
    "One row per occupied voxel (rowmap/structure.py VOXEL_M) of the row's stuff surfaces within "
    "fruit_count.max_depth_m: stems and leaves of the near row, floor, pipes; fruits and void pixels are left out. "
    "Built from the recorded depth of every fused frame, its fused labels and its fused camera pose.",
    col("x_m", pa.float32(), "mean x of the voxel's points in the row frame", "m"),
    col("y_m", pa.float32(), "mean y of the voxel's points in the row frame", "m"),
    col("z_m", pa.float32(), "mean z of the voxel's points in the row frame", "m"),
    col("n_points", pa.int32(), "depth pixels averaged into the voxel (after the per-frame subsampling)", "points"),
    col("class_id", pa.int32(), "the stuff class most of those pixels had (pipeline/classes.py)"),
)
