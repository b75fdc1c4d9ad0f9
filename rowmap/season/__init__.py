"""A season of one row: the fruits of each recording date registered to the first date and linked into tracks.

    registration.py   a date's row frame onto the season frame: rigid (x, y, z, yaw) plus a correction along
                      the row, on the rows' static structure (rowmap/structure.py) and their fruits
    association.py    one assignment of a date's fruits to the open tracks (Hungarian, gated)
    tracks.py         the season: dates in order -> fruit_tracks, track summary, registrations
    scoring.py        scores against a synthetic season's ground truth

Inputs are the rows' own output tables (fruits, panoptic_frames, structure), never their images, so a
season's memory is bounded by those tables. docs/season.md describes the method and the tables.
"""
