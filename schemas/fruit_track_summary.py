"""fruit_track_summary: one row per fruit track of a season: when it was seen, grew, ripened, was picked."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "fruit_track_summary",
    "One row per fruit track of a row's season (`pag track`, docs/season.md): its dates, growth and ripening, "
    "and the date it was found harvested.",
    col("track_id", pa.int32(), "season-wide fruit identity (fruit_tracks.track_id)"),
    col("n_dates", pa.int32(), "dates the fruit was observed on", "dates"),
    col("first_seq", pa.string(), "sequence of its first observation"),
    col("first_date", pa.date32(), "date of its first observation", nullable=True),
    col("last_date", pa.date32(), "date of its last observation", nullable=True),
    col("first_day", pa.float64(), "day of its first observation (days since the season's first date)", "days"),
    col("last_day", pa.float64(), "day of its last observation", "days"),
    col("set_date", pa.date32(), "date it was first seen as a newly set fruit (event 'set'), else null",
        nullable=True),
    col("date_red", pa.date32(), "first date it was red, else null", nullable=True),
    col("days_to_red", pa.float64(), "days from its first observation to its first red one (0 = red when "
        "first seen; null if never red)", "days", nullable=True),
    col("date_harvested", pa.date32(), "date it was found harvested, else null", nullable=True),
    col("day_harvested", pa.float64(), "day it was found harvested, else null", "days", nullable=True),
    col("growth_mm_per_day", pa.float64(), "least-squares slope of its diameter over its dates (null with "
        "fewer than 2 measured dates)", "mm/day", nullable=True),
    col("diameter_first_m", pa.float64(), "diameter at its first observation", "m", nullable=True),
    col("diameter_last_m", pa.float64(), "diameter at its last observation", "m", nullable=True),
    col("class_first", pa.string(), "class at its first observation"),
    col("class_last", pa.string(), "class at its last observation"),
    col("x_m", pa.float64(), "last centre x in the season frame", "m"),
    col("y_m", pa.float64(), "last centre y in the season frame", "m"),
    col("z_m", pa.float64(), "last centre z in the season frame", "m"),
)
