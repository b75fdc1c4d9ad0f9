"""renders: every image file nerf_fit rendered, by window, frame and kind."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "renders",
    "One row per image file a fitted window rendered: its validation frames' colour and depth and, with the "
    "panoptic phase, their semantic and instance images and fruit probability (rowmap/renders.py says how each "
    "kind is encoded). "
    "Stages after nerf_fit find renders here, never by building file names. A failed window has no rows.",
    col("window_id", pa.int32(), "window that rendered the file (windows.window_id)"),
    col("frame_id", pa.int32(), "frame rendered (frames.frame_id; a validation frame of the window)"),
    col("kind", pa.string(), "'rgb' (8-bit colour), 'depth' (16-bit mm, 0 = none), 'semantic' (8-bit class id, "
        "255 = void), 'instance' (16-bit window-local slot id, 0 = stuff or none) or 'fruit' (8-bit probability "
        "of the thing classes x 255)"),
    col("path", pa.string(), "the PNG, relative to data/"),
)
