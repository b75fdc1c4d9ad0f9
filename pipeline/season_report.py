"""The season report: one self-contained HTML page over a tracked season (figures embedded as PNG).

Growth curves (diameter over days per track), counts by class per date with the set and harvested fruits
of each interval, a map of the row (season frame, x along the row, z up) with each fruit coloured by its age
(days since its first observation), the dates table (registration) and, with ground truth, the scores.
"""
from __future__ import annotations

import html

import numpy as np
import pandas as pd

from pipeline.campaign_report import CSS, THINGS, _figure_uri, _pyplot
from rowmap.season.tracks import Season


def growth_chart(tracks: pd.DataFrame) -> str:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.0, 3.6), dpi=110)
    seen = tracks[tracks.fruit_id.notna()]
    colour = {c.name: np.array(c.rgb) / 255 for c in THINGS}
    for _, t in seen.groupby("track_id"):
        ax.plot(t.day, t.diameter_m * 1000, "-", color="0.6", linewidth=0.7)
        ax.scatter(t.day, t.diameter_m * 1000, c=[colour.get(c, (0.5, 0.5, 0.5)) for c in t.class_name], s=12,
                   edgecolors="k", linewidths=0.3, zorder=3)
    ax.set_xlabel("day of the season")
    ax.set_ylabel("diameter (mm)")
    ax.set_title("growth of every tracked fruit (colour = class on that date)", fontsize=9)
    return _figure_uri(fig)


def counts_chart(tracks: pd.DataFrame, dates: pd.DataFrame) -> str:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.0, 3.6), dpi=110)
    x = np.arange(len(dates))
    bottom = np.zeros(len(dates))
    seen = tracks[tracks.fruit_id.notna()]
    for c in THINGS:
        v = np.array([((seen.seq == s) & (seen.class_name == c.name)).sum() for s in dates.seq], np.float64)
        ax.bar(x, v, 0.6, bottom=bottom, color=np.array(c.rgb) / 255, edgecolor="k", linewidth=0.4, label=c.name)
        bottom += v
    ax.plot(x, dates.harvested, "kx-", label="harvested since the date before")
    ax.plot(x, dates.set, "o--", color="tab:green", label="set since the date before")
    ax.set_xticks(x, [f"{s}\nday {d:.0f}" for s, d in zip(dates.seq, dates.day)], fontsize=7)
    ax.set_ylabel("fruits")
    ax.legend(fontsize=7)
    return _figure_uri(fig)


def age_map(tracks: pd.DataFrame) -> str:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8.0, 3.0), dpi=110)
    seen = tracks[tracks.fruit_id.notna()]
    last = seen.sort_values("day").groupby("track_id").tail(1)
    first_day = seen.groupby("track_id").day.min()
    age = last.day.to_numpy() - last.track_id.map(first_day).to_numpy()
    sc = ax.scatter(last.x_m, last.z_m, c=age, s=np.clip(np.nan_to_num(last.diameter_m.to_numpy(), nan=0.05), 0.02, 0.12)
                    * 1500, cmap="viridis", edgecolors="k", linewidths=0.3)
    fig.colorbar(sc, ax=ax, label="days since first seen")
    ax.set_aspect("equal")
    ax.set_xlabel("x along the row (m, season frame)")
    ax.set_ylabel("z (m)")
    ax.set_title("every track at its last observation", fontsize=9)
    return _figure_uri(fig)


def section(season: Season, scores: dict[str, float], level: int = 2) -> str:
    """The season's figures, dates and scores as HTML (headings at `level`), for the season report and the
    campaign report's season section."""
    t, d = season.tracks, season.dates
    h = f"h{level}"
    parts = []
    if len(t):
        parts += [f"<{h}>Growth</{h}>", f"<img src='{growth_chart(t)}' alt='growth curves'>",
                  f"<{h}>Fruits by class, set and harvested</{h}>",
                  f"<img src='{counts_chart(t, d)}' alt='counts by class per date'>",
                  f"<{h}>Row map by fruit age</{h}>", f"<img src='{age_map(t)}' alt='row map by fruit age'>"]
    parts += [f"<{h}>Dates</{h}>", d.to_html(classes="t", index=False, float_format=lambda v: f"{v:.3f}")]
    if scores:
        parts += [f"<{h}>Scores</{h}>", "<table class='t'>"] + [
            f"<tr><th>{html.escape(k)}</th><td>{v:.4g}</td></tr>" for k, v in scores.items()] + ["</table>"]
    return "\n".join(parts)


def render(season: Season, scores: dict[str, float]) -> str:
    t, d = season.tracks, season.dates
    return "\n".join([
        f"<!doctype html><html><head><meta charset='utf-8'><title>Season</title><style>{CSS}</style></head><body>",
        f"<h1>Season of {len(d)} dates, {t.track_id.nunique()} fruit tracks</h1>", section(season, scores),
        "</body></html>"])
