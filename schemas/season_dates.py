"""season_dates: one row per recording date of a season: its registration and what the tracks did."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "season_dates",
    "One row per recording date of a row's season (`pag track`): the rigid transform that registers the date's "
    "row frame onto the season frame (the first date's; identity there), how many fruit pairs agree with it, "
    "and the date's fruits, continued tracks and events.",
    col("seq", pa.string(), "sequence of the date"),
    col("date", pa.date32(), "recording date (from the name, the stamps or SEQ@DATE)", nullable=True),
    col("day", pa.float64(), "days since the season's first date", "days"),
    col("fruits", pa.int32(), "counted fruits of the row on that date", "fruits"),
    col("continued", pa.int32(), "of those, fruits that continue a track from an earlier date", "fruits"),
    col("set", pa.int32(), "set events on that date", "fruits"),
    col("harvested", pa.int32(), "harvested events on that date", "fruits"),
    col("lost", pa.int32(), "tracks lost on that date: fruits never seen mixed or red, not seen where it recorded "
        "less than track.ripen_days after their last sighting (false fruits of an earlier date's map, or fruits it "
        "missed); not harvested", "fruits"),
    col("registered_on", pa.string(), "what the date was registered on: 'structure' (its stems, leaves and floor: "
        "structure.parquet), 'fruits' (the fruits' consensus) or 'first date' (the season frame itself)"),
    col("registration_inliers", pa.int32(), "fruit pairs within the final inlier radius after registration",
        "fruits"),
    col("registration_rms_m", pa.float64(), "RMS distance of those pairs (null without pairs)", "m", nullable=True),
    col("tx_m", pa.float64(), "registration translation x (row frame -> season frame)", "m"),
    col("ty_m", pa.float64(), "registration translation y", "m"),
    col("tz_m", pa.float64(), "registration translation z", "m"),
    col("yaw_deg", pa.float64(), "registration rotation about z", "deg"),
    col("correction_max_m", pa.float64(), "largest correction along the row the registration adds to its rigid "
        "part, over the date's camera positions (the two dates' different odometry drift)", "m"),
    col("stretch_x_min_m", pa.float64(), "start of the stretch of row the date recorded (season frame x)", "m"),
    col("stretch_x_max_m", pa.float64(), "end of that stretch", "m"),
)
