"""The campaign report: one self-contained HTML page over the rows of a campaign (figures embedded as PNG).

Counts per row and class (bar chart), the fruit size distribution per row (box plot of the counted
fruits' diameters), a table of the rows (rows.parquet) with links to each row's own report, and the
rows that failed with their message.
"""
from __future__ import annotations

import base64
import html
import io

import numpy as np
import pandas as pd

from pipeline.classes import DEFAULT_CLASSES

THINGS = tuple(c for c in DEFAULT_CLASSES if c.is_thing)
CSS = """body{font-family:system-ui,sans-serif;margin:1.5em;max-width:1600px;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #ccc;margin-top:1.6em}
table.t{border-collapse:collapse;font-size:0.85em}table.t td,table.t th{padding:2px 8px;border-bottom:1px solid #eee;
text-align:right}.note{color:#a40}"""


def _figure_uri(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def row_label(row: pd.Series) -> str:
    return f"{row.seq}\n{row.date}" if pd.notna(row.date) else str(row.seq)


def counts_chart(rows: pd.DataFrame) -> str:
    """Grouped bars: counted fruits per row (x) and class (bar colour)."""
    plt = _pyplot()
    from matplotlib.ticker import MaxNLocator

    fig, ax = plt.subplots(figsize=(max(5.0, 1.1 * len(rows) + 2), 3.6), dpi=110)
    x = np.arange(len(rows))
    width = 0.8 / len(THINGS)
    for j, c in enumerate(THINGS):
        values = rows[f"count_{c.name}"].fillna(0).to_numpy(np.float64)
        bars = ax.bar(x + (j - (len(THINGS) - 1) / 2) * width, values, width, color=np.array(c.rgb) / 255,
                      edgecolor="k", linewidth=0.4, label=c.name)
        ax.bar_label(bars, fmt="%d", fontsize=7)
    ax.set_xticks(x, [row_label(r) for _, r in rows.iterrows()], fontsize=8)
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("counted fruits")
    ax.set_title("Fruits per row and class")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1))
    return _figure_uri(fig)


def size_chart(rows: pd.DataFrame, fruits: pd.DataFrame) -> str:
    """Box plot (with the fruits as dots) of the counted fruits' diameters per row, in mm."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(max(5.0, 1.1 * len(rows) + 2), 3.6), dpi=110)
    data = []
    for seq in rows.seq:
        f = fruits[(fruits.seq == seq) & fruits.counted.astype(bool)]
        data.append(f.diameter_m.dropna().to_numpy(np.float64) * 1000)
    positions = np.arange(1, len(data) + 1)
    ax.boxplot([d if len(d) else [np.nan] for d in data], positions=positions, widths=0.5, showfliers=False)
    rng = np.random.default_rng(0)  # horizontal jitter of the dots only
    for p, d in zip(positions, data):
        ax.scatter(p + rng.uniform(-0.15, 0.15, len(d)), d, s=8, color="tab:blue", alpha=0.6, zorder=3)
    ax.set_xticks(positions, [row_label(r) for _, r in rows.iterrows()], fontsize=8)
    ax.set_ylabel("diameter [mm]")
    ax.set_title("Fruit size per row (counted fruits with a diameter)")
    ax.grid(axis="y", alpha=0.3)
    return _figure_uri(fig)


def rows_table(rows: pd.DataFrame) -> str:
    cols = ["seq", "date", "status", "n_frames", "row_length_m", "windows", "fruits",
            *[f"count_{c.name}" for c in THINGS], "fruits_per_m", "mean_diameter_m", "val_psnr", "pq", "count_gt"]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols + ["report"])
    body = []
    for _, r in rows.iterrows():
        cells = []
        for c in cols:
            v = r[c]
            text = "-" if v is None or (not isinstance(v, str) and pd.isna(v)) else (
                f"{v:.4g}" if isinstance(v, float) else str(v))
            cells.append(f"<td>{html.escape(text)}</td>")
        # this page is data/processed/_campaign/report.html; a row's is data/processed/<SEQ>/report/report.html
        link = (f'<a href="../{html.escape(str(r.report_path).removeprefix("processed/"))}">report</a>'
                if r.report_path else "-")
        body.append(f"<tr>{''.join(cells)}<td>{link}</td></tr>")
    return f'<table class="t"><tr>{head}</tr>{"".join(body)}</table>'


def render(rows: pd.DataFrame, tables: dict[str, pd.DataFrame | None], season: str = "") -> str:
    """The page. `rows`: rows.parquet's content; `tables`: the rows' tables concatenated, with a `seq` column;
    `season`: the season section's HTML (pipeline.season_report.section) of a campaign run with --track."""
    ok = rows[rows.status == "ok"]
    failed = rows[rows.status != "ok"]
    fruits = tables.get("fruits")
    n_fruits = int(ok.fruits.fillna(0).sum())
    parts = ["<h1>PAg-NeRF campaign report</h1>",
             f"<p>{len(ok)} of {len(rows)} rows finished; {n_fruits} fruits counted over "
             f"{ok.row_length_m.fillna(0).sum():.1f} m of row. The tables behind this page are in this folder "
             f"(rows.parquet and the Hive-partitioned fruits/, counts/, window_metrics/, evaluation/).</p>"]
    if len(failed):
        parts.append("<p class='note'>Failed rows (not in the figures or the partitioned tables): " + "; ".join(
            f"{html.escape(str(r.seq))}: {html.escape(str(r.error))}" for r in failed.itertuples()) + "</p>")
    parts.append("<h2>Counts</h2>")
    parts.append(f'<img src="{counts_chart(ok)}" alt="counts per row and class">' if len(ok) else
                 "<p>No finished row.</p>")
    parts.append("<h2>Fruit size</h2>")
    parts.append(f'<img src="{size_chart(ok, fruits)}" alt="diameter per row">'
                 if len(ok) and fruits is not None and len(fruits) else "<p>No fruit.</p>")
    parts.append("<h2>Rows</h2>" + rows_table(rows))
    if season:
        parts.append("<h2>Season</h2><p>The finished rows tracked as dates of one row (`pag campaign --track`; "
                     "the season dataset is data/processed/_season/, docs/season.md).</p>" + season)
    return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>PAg-NeRF campaign report</title>"
            f"<style>{CSS}</style></head><body>{''.join(parts)}</body></html>")
