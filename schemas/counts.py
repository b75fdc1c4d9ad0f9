"""counts: near-row fruits per ripeness class."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "counts",
    "One row per fruit class (every thing class, also with count 0): near-row fruits of fruits.parquet "
    "(near_row = true); far-row fruits beyond fruit_count.max_depth_m are not counted.",
    col("class_id", pa.int32(), "ripeness class id (pipeline/classes.py)"),
    col("class_name", pa.string(), "class name"),
    col("count", pa.int32(), "near-row fruits of that class", "fruits"),
    col("mean_diameter_m", pa.float64(), "mean diameter_m of those fruits (null if none has one)", "m", nullable=True),
)
