"""windows: which frames each NeRF window trains and validates on."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "windows",
    "One row per (window, frame). A window is centred on a labelled frame and spans half_width frames "
    "each side (clipped at the sequence ends); with windows.cover_row (default) windows next to frames in no "
    "window grow into them and filler windows (no labelled centre) cover longer stretches, so every frame is "
    "in a window and neighbours share frames. Every windows.val_every-th frame validates (counted from the "
    "first centre), the rest train; labelled frames always validate. A frame has the same split in every "
    "window.",
    col("window_id", pa.int32(), "window index, from 0, in order of the centre frame"),
    col("frame_id", pa.int32(), "frame (frames.frame_id)"),
    col("center_frame_id", pa.int32(), "the frame the window is centred on (labelled, except for filler windows)"),
    col("offset", pa.int32(), "frame_id - center_frame_id", "frames"),
    col("split", pa.string(), "'train' or 'val'"),
    col("is_center", pa.bool_(), "true for the labelled centre frame (evaluation frame); false in every row "
        "of a filler window"),
    col("n_windows", pa.int32(), "how many windows contain this frame (> 1 where windows overlap)"),
)
