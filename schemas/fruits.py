"""fruits: one row per fruit of the row, with a stable id, position, size, ripeness and views."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "fruits",
    "One row per row-level fruit (the instance id of the fused panoptic PNGs). Positions are in the row frame "
    "(the world frame of frames.parquet near the row start, windows chained through the frames they share; "
    "x along the row, y left, z up). Sizes come from the fruit's visible surface: its pixels in every fused "
    "frame unprojected with the NeRF depth render and the frame's row-frame pose (panoptic_frames), outliers "
    "rejected by a MAD test on the distance to the median. Fruits whose median viewing depth is beyond "
    "fruit_count.max_depth_m (the far row) have near_row = false, and fragments (seen in too few frames or "
    "with too few points) counted = false; neither is in counts.parquet.",
    col("fruit_id", pa.int32(), "row-level fruit id (1..n, increasing along the row)"),
    col("class_id", pa.int32(), "ripeness class (pipeline/classes.py): majority over the frames it is seen in"),
    col("class_name", pa.string(), "name of class_id"),
    col("class_confidence", pa.float64(), "share of the fruit's frames whose majority class is class_id", "fraction"),
    col("x_m", pa.float64(), "centre x (world): the surface fit's centre (the median of the points when no fit "
        "is plausible)", "m"),
    col("y_m", pa.float64(), "centre y (world)", "m"),
    col("z_m", pa.float64(), "centre z (world)", "m"),
    col("diameter_m", pa.float64(), "fruit width estimated by fruit_count.diameter_method (default: least-squares "
        "vertical-axis spheroid fit to the visible surface); null with fewer than fruit_count.min_points points",
        "m", nullable=True),
    col("diameter_spheroid_m", pa.float64(), "equatorial diameter of the least-squares spheroid (vertical axis) fit",
        "m", nullable=True),
    col("diameter_sphere_m", pa.float64(), "diameter of the least-squares (geometric) sphere fit", "m", nullable=True),
    col("diameter_pca_m", pa.float64(), "second-largest principal extent of the points (2.5-97.5 percentile "
        "range along the PCA axis); biased on a half-seen surface, kept for comparison", "m", nullable=True),
    col("axis1_m", pa.float64(), "largest principal extent (2.5-97.5 percentile range)", "m", nullable=True),
    col("axis2_m", pa.float64(), "middle principal extent", "m", nullable=True),
    col("axis3_m", pa.float64(), "smallest principal extent (depth of the visible cap)", "m", nullable=True),
    col("height_m", pa.float64(), "vertical extent (2.5-97.5 percentile range of z): the fruit length of a "
        "hanging fruit", "m", nullable=True),
    col("median_depth_m", pa.float64(), "median camera depth of the fruit's pixels over its frames", "m"),
    col("near_row", pa.bool_(), "median_depth_m <= fruit_count.max_depth_m; false = far row (not counted)"),
    col("counted", pa.bool_(), "in counts.parquet: near_row, seen in >= fruit_count.min_count_frames fused frames "
        "and with >= fruit_count.min_count_points points, and not unconfirmed by the detector (detector_p) "
        "(false = far row, a fragment or unconfirmed); a fruit the detector alone tracks at a recording's end "
        "(end_track_frames) is counted"),
    col("n_confirmed_frames", pa.int32(), "fused frames in which the detector's segments cover >= "
        "fruit_count.detector_cover of the fruit's pixels (null without detector images)", "frames", nullable=True),
    col("detector_p", pa.float64(), "chance that a real fruit is confirmed in as few of its fused frames, at the "
        "row's confirmation rate (binomial); below fruit_count.detector_alpha, with under half that rate, it is "
        "not counted, as is a fruit with under half that rate and no plausible surface fit (null without "
        "detector images)", "fraction", nullable=True),
    col("n_points", pa.int32(), "3D points kept after outlier rejection", "points"),
    col("n_outliers", pa.int32(), "3D points rejected by the MAD test", "points"),
    col("n_frames", pa.int32(), "fused frames the fruit appears in", "frames"),
    col("n_windows", pa.int32(), "windows whose instance slots were fused into this fruit", "windows"),
    col("first_frame_id", pa.int32(), "first fused frame it appears in"),
    col("last_frame_id", pa.int32(), "last fused frame it appears in (for an end-track fruit: its detector frames)"),
    col("end_track_frames", pa.int32(), "a fruit at a recording's end (or in a failed window's frames) that no two "
        "fused frames see, tracked by the detector alone (fruit_count.end_tracks; no fused pixels, n_frames 0): the "
        "frames it is tracked in; null for a fused fruit", "frames", nullable=True),
)
