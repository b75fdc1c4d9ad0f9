"""fruit_tracks: one row per (fruit track, recording date) of a season: the fruit seen, set or harvested."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "fruit_tracks",
    "One row per observation of a tracked fruit on a recording date of one row's season (`pag track`, "
    "docs/season.md), plus a row on the date a fruit is found harvested. Written Hive-partitioned by seq "
    "(fruit_tracks/seq=<SEQ>/part-0.parquet, the recording date as a first column `date`). Positions are in the "
    "season frame: the first date's row frame, every later date registered onto it.",
    col("track_id", pa.int32(), "season-wide fruit identity (1..n, in order of first date, then along the row)"),
    col("day", pa.float64(), "days since the season's first recording (from the rows' first frame stamps, else "
        "their dates)", "days"),
    col("fruit_id", pa.int32(), "the fruit's id in that date's fruits.parquet (null on a harvested row)",
        nullable=True),
    col("diameter_m", pa.float64(), "fruits.parquet diameter_m on that date (null if not measured or harvested)",
        "m", nullable=True),
    col("class_name", pa.string(), "ripeness class on that date (null on a harvested row)", nullable=True),
    col("event", pa.string(), "'set' (first seen, small, where the previous date saw no fruit), 'present' or "
        "'harvested' (a fruit once seen mixed or red, or green track.ripen_days or more before, gone from where the "
        "date recorded; the row repeats the last position; a green fruit that goes sooner is lost, with no row)"),
    col("x_m", pa.float64(), "centre x in the season frame", "m"),
    col("y_m", pa.float64(), "centre y in the season frame", "m"),
    col("z_m", pa.float64(), "centre z in the season frame", "m"),
)
