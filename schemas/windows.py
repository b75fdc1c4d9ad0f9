"""windows: which frames each NeRF window trains and validates on."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "windows",
    "One row per (window, frame). A window is centred on a labelled frame and spans half_width frames "
    "each side (clipped at the sequence ends). Odd offsets train, even offsets validate; the centre "
    "frame (offset 0) is a validation frame and the evaluation frame. Windows may overlap.",
    col("window_id", pa.int32(), "window index, from 0, in order of the centre frame"),
    col("frame_id", pa.int32(), "frame (frames.frame_id)"),
    col("center_frame_id", pa.int32(), "the labelled frame the window is centred on"),
    col("offset", pa.int32(), "frame_id - center_frame_id", "frames"),
    col("split", pa.string(), "'train' or 'val'"),
    col("is_center", pa.bool_(), "true for the labelled centre frame (evaluation frame)"),
    col("n_windows", pa.int32(), "how many windows contain this frame (> 1 where windows overlap)"),
)
