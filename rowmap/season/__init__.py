"""A season of one row: the fruits of each recording date registered to the first date and linked into tracks.

    registration.py   rigid (x, y, z, yaw) transform of a date's row frame onto the season frame
    association.py    one assignment of a date's fruits to the open tracks (Hungarian, gated)
    tracks.py         the season: dates in order -> fruit_tracks, track summary, registrations
    scoring.py        scores against a synthetic season's ground truth

Inputs are the rows' own output tables (fruits, panoptic_frames), never their images, so a season's
memory is bounded by its fruit tables. docs/season.md describes the method and the tables.
"""
