"""input_checks: what ingest found in the recording: totals, skips and repairs with their counts, and notes."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "input_checks",
    "One row per count or note of the ingest stage summary (README.md, section Bad input, lists the checks): totals "
    "(frames, labelled, segments), skips (e.g. skipped_no_odometry, frames_with_one_detector_png_missing) and "
    "repairs (e.g. odometry_out_of_order), the source and detections format read, and notes naming files.",
    col("check", pa.string(), "name of the count (e.g. skipped_duplicate_frame), or 'note', 'source', "
                              "'detections_format'"),
    col("count", pa.int64(), "how many (frames, segments, rows or pixels, as the name says); null for notes",
        nullable=True),
    col("note", pa.string(), "text of a note or of a named value ('' for counts)"),
)
