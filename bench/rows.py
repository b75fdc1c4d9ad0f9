"""The whole pipeline on a fixed family of synthetic rows (bench/_row_family.py): count, identity, panoptic
and size errors, PSNR and cost per row, with the mean and the worst row.

    pag bench rows [--rows NAME,NAME] [--quick | --holdout | --unseen] [--fit-seed N] [--force] [--data-root data]
                   [--out data/bench]

Each row is the sequence synth_rows_<name> under --data-root (the normal pipeline outputs, report included).
Checkpointed: a finished row's results are kept in <out>/rows/<name>.json and the row is skipped on a rerun
(--force reruns it); a row stopped half-way resumes at the stage it stopped in. The table is rebuilt from
every finished row each time. `--quick` runs 4 rows with tiny images and few steps (a smoke test of the
harness; its numbers mean nothing) into rows_quick.* and sequences synth_rowsq_<name>.
`--holdout` runs the held-out rows (bench/_row_family.py HOLDOUT: seeds and knob values in no family row)
into rows_holdout.*, the check that what holds on the family is not tuned to it.
`--unseen` runs the unseen rows (UNSEEN: seeds and knobs in no other row, read once when a design is final)
into rows_unseen.*.
`--fit-seed N` (N >= 1) fits every window with nerf_fit.seed = N (the same recording, other random rays and
initial weights) into rows_seed<N>.* (rows_holdout_seed<N>.* with --holdout) and sequences
synth_rows_<name>_seed<N>: the spread between seeds is the fit-to-fit variance any change of the model has
to exceed to be seen.
Writes <out>/rows.parquet (one row per family row, then 'mean' and 'worst') and <out>/rows.png.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from bench._common import write_parquet
from bench._pipeline import QUALITY, TINY, quality, run_variant, settings
from bench._row_family import FAMILY, HOLDOUT, QUICK, UNSEEN, family_row
from pipeline.io import atomic_write_bytes

ID_FAILURES = {f"id_fail_{k}": (("row", f"id_fail_{k}"),) for k in ("unlabelled", "shared", "split")}
"""Why fruits fail the row-level ID consistency, in fruits (evaluate's id_fail_*; a fruit can fail in several
ways): 'unlabelled' = in some frame no fused id covers most of it, 'shared' = an id it carries is another
fruit's somewhere, 'split' = it carries two ids."""
LOWER_IS_BETTER = {"diameter_median_err_m", "minutes", "peak_rss_mb", *ID_FAILURES}
"""Columns whose worst value is the largest; count_error_rel's worst is the largest magnitude; for the other
quality columns the worst is the smallest."""


def row_settings(name: str, quick: bool, fit_seed: int = 0) -> list[str]:
    knobs = {f"synth.{k}": v for k, v in family_row(name).knobs().items()}
    if quick:
        knobs.update(TINY)
        knobs.update({"synth.n_frames": 14, "synth.n_labelled": 2})
    if fit_seed:
        knobs["nerf_fit.seed"] = fit_seed
    return settings(knobs)


def row_seq(name: str, quick: bool = False, fit_seed: int = 0) -> str:
    """The sequence a row runs as: synth_rows_<name> (synth_rowsq_ with --quick, _seed<N> with --fit-seed)."""
    return f"synth_rows{'q' if quick else ''}_{name}" + (f"_seed{fit_seed}" if fit_seed else "")


def run_row(name: str, quick: bool, data_root: Path, force: bool, fit_seed: int = 0) -> dict:
    seq = row_seq(name, quick, fit_seed)
    run = run_variant(seq, row_settings(name, quick, fit_seed), data_root, force=force)
    rec = {"row": name, **family_row(name).knobs(), **({"fit_seed": fit_seed} if fit_seed else {}),
           **quality(data_root, seq, QUALITY | ID_FAILURES),
           "minutes": run.stage_minutes(),
           "peak_rss_mb": run.peak_rss_mb(), "seq": seq}
    if quick:
        rec.update(n_frames=14, n_labelled=2)
    return rec


def summarise(rows: pd.DataFrame) -> pd.DataFrame:
    """The rows, then a 'mean' row and a 'worst' row of every quality and cost column."""
    cols = [*QUALITY, *(c for c in ID_FAILURES if c in rows), "minutes", "peak_rss_mb"]
    mean = {"row": "mean", **{c: float(rows[c].mean()) for c in cols}}
    worst = {"row": "worst"}
    for c in cols:
        v = rows[c].dropna()
        if v.empty:
            worst[c] = float("nan")
        elif c == "count_error_rel":
            worst[c] = float(v.iloc[int(np.argmax(np.abs(v.to_numpy())))])
        else:
            worst[c] = float(v.max() if c in LOWER_IS_BETTER else v.min())
    return pd.concat([rows, pd.DataFrame([mean, worst])], ignore_index=True)


def plot(df: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = df[~df.row.isin(["mean", "worst"])]
    panels = [("count_error_rel", "count error (rel.)"), ("recall", "recall"), ("precision", "precision"),
              ("row_id_consistency", "row ID consistency"), ("pq", "PQ (bars) / detector PQ (dots)"),
              ("diameter_median_err_m", "median diameter error (m)"), ("psnr_db", "val PSNR (dB)"),
              ("minutes", "minutes")]
    fig, axes = plt.subplots(2, 4, figsize=(14, 6))
    x = np.arange(len(rows))
    for ax, (col, title) in zip(axes.ravel(), panels):
        ax.bar(x, rows[col].to_numpy(np.float64), color="#48c")
        if col == "pq":
            ax.plot(x, rows["pq_detector"].to_numpy(np.float64), "o", color="#c44")
        mean = df.loc[df.row == "mean", col]
        if len(mean) and np.isfinite(mean.iloc[0]):
            ax.axhline(float(mean.iloc[0]), color="#444", lw=0.8, ls="--")
        ax.set_title(title, fontsize=9)
        ax.set_xticks(x, rows.row, rotation=60, fontsize=7)
    fig.suptitle("pag bench rows (dashed: mean over rows)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(names: list[str], quick: bool = False, force: bool = False, data_root: Path = Path("data"),
        out_dir: Path = Path("data/bench"), tag: str = "", fit_seed: int = 0) -> pd.DataFrame:
    """Runs the rows `names` not done yet, then rebuilds the table <out_dir>/<tag>.parquet from every finished
    row of <out_dir>/<tag>/ (tag: 'rows', 'rows_quick' with `quick`, or as given)."""
    tag = tag or ("rows_quick" if quick else "rows")
    done_dir = out_dir / tag
    done_dir.mkdir(parents=True, exist_ok=True)
    for name in names:
        done = done_dir / f"{name}.json"
        if done.is_file() and not force:
            print(f"[bench rows] {name}: done before, skipped ({done})", file=sys.stderr)
            continue
        print(f"[bench rows] {name}: running", file=sys.stderr)
        rec = run_row(name, quick, data_root, force, fit_seed)
        atomic_write_bytes(done, json.dumps(rec, indent=1).encode())
        print(f"[bench rows] {name}: {rec['minutes']:.1f} min, count error {rec['count_error_rel']:+.3f}, "
              f"PQ {rec['pq']:.3f}", file=sys.stderr)
    order = [r.name for r in (*FAMILY, *HOLDOUT, *UNSEEN)]
    recs = [json.loads(p.read_text()) for p in done_dir.glob("*.json")]
    recs.sort(key=lambda r: order.index(r["row"]) if r["row"] in order else len(order))
    df = summarise(pd.DataFrame(recs))
    write_parquet(df, out_dir / f"{tag}.parquet")
    plot(df, out_dir / f"{tag}.png")
    return df


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench rows", description=__doc__.split("\n")[0])
    p.add_argument("--rows", default="", help=f"comma-separated subset of {[r.name for r in FAMILY]} (default: all), "
                   f"or with --holdout of {[r.name for r in HOLDOUT]}")
    p.add_argument("--quick", action="store_true", help=f"the 4-row smoke run {list(QUICK)} with tiny settings")
    p.add_argument("--holdout", action="store_true",
                   help=f"the held-out rows {[r.name for r in HOLDOUT]} (in no family row's seed or knobs)")
    p.add_argument("--unseen", action="store_true",
                   help=f"the unseen rows {[r.name for r in UNSEEN]} (read once, when a design is final)")
    p.add_argument("--fit-seed", type=int, default=0,
                   help="nerf_fit.seed of every window (>= 1; own tables rows_seed<N>.*): the fit-to-fit spread")
    p.add_argument("--force", action="store_true", help="rerun rows (and their stages) that are done")
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    if a.quick + a.holdout + a.unseen > 1:
        p.error("--quick, --holdout and --unseen exclude each other")
    group = "holdout" if a.holdout else "unseen" if a.unseen else "family"
    members = [r.name for r in {"holdout": HOLDOUT, "unseen": UNSEEN, "family": FAMILY}[group]]
    names = [n.strip() for n in a.rows.split(",") if n.strip()] or (list(QUICK) if a.quick else members)
    for n in names:
        family_row(n)  # unknown names fail before anything runs
    if not a.quick and set(names) - set(members):
        p.error(f"{sorted(set(names) - set(members))} are not {group} rows: pick the rows of one group "
                f"(--holdout, --unseen or neither; the tables are kept apart)")
    if a.fit_seed < 0:
        p.error(f"--fit-seed must be >= 1 (0 = the seed of the plain run), got {a.fit_seed}")
    tag = ("rows_quick" if a.quick else "rows" if group == "family" else f"rows_{group}") + (
        f"_seed{a.fit_seed}" if a.fit_seed else "")
    df = run(names, a.quick, a.force, a.data_root, a.out, tag, a.fit_seed)
    cols = ["row", "count_error_rel", "recall", "precision", "row_id_consistency", "pq", "pq_detector", "psnr_db",
            "minutes"]
    print(df[cols].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print(f"wrote {a.out / tag}.parquet and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
