"""fruit_slots: how panoptic_fusion mapped each window's instance slots to row-level fruits."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "fruit_slots",
    "One row per window-local fruit: a (window, instance slot, part) of a window's panoptic renders. A slot "
    "whose per-frame 3D centres fall into several clusters (the NeRF gave one slot to fruits far apart) is "
    "split into parts 0, 1, ... Each part is mapped to one row-level fruit id (0 = dropped: too few pixels "
    "or no valid depth). Centres are those the association matched on, from the slot's pixels unprojected "
    "with the rendered depth and the window's refined pose, in the row frame: the centre of a sphere fitted "
    "to them, of a sphere with the row's median fitted radius behind them where that fit is not plausible, "
    "or their robust median where no sphere fits.",
    col("window_id", pa.int32(), "window (windows.window_id)"),
    col("slot", pa.int32(), "window-local instance slot of the NeRF's instance PNGs"),
    col("part", pa.int32(), "cluster index of the slot's per-frame centres (0 unless the slot was split)"),
    col("fruit_id", pa.int32(), "row-level fruit id (fruits.fruit_id); 0 = dropped"),
    col("class_id", pa.int32(), "majority semantic class of the slot's pixels"),
    col("n_frames", pa.int32(), "validation frames of the window in which the slot appears"),
    col("n_px", pa.int64(), "pixels of the slot over those frames", "px"),
    col("x_m", pa.float64(), "centre x (row frame)", "m", nullable=True),
    col("y_m", pa.float64(), "centre y (row frame)", "m", nullable=True),
    col("z_m", pa.float64(), "centre z (row frame)", "m", nullable=True),
    col("drop_reason", pa.string(), "why the slot got no fruit id ('' if it has one)"),
)
