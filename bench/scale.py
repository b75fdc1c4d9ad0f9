"""How the whole pipeline's cost grows with row length and image size, with quality beside it.

    pag bench scale [--frames 60,120,240,480] [--sizes 320x180,640x360,1280x720] [--quick] [--force]
                    [--data-root data] [--out data/bench]

Two sweeps of synthetic rows through every stage: frames (at the first size) and pixels (at the first frame
count); the shared point runs once. Label density stays that of the default row (one labelled frame, i.e.
one window, per 40 frames, at least one), so a longer row also has more windows. Per variant and stage it
records the wall time and the peak memory of the process tree (workers included; the runner's manifest
records), and per variant the quality columns of bench/_pipeline.py (validation PSNR, PQ, count error, ...).
Per stage and sweep it fits the growth exponent (log-log slope: 1 = linear in frames or in pixels).
Sequences are synth_scale_<frames>f_<W>x<H> under --data-root; a rerun skips stages that are up to date.
Writes <out>/scale.parquet, <out>/scale_exponents.parquet and <out>/scale.png (`--quick`: scale_quick.*, with
tiny sizes and few steps: a smoke test of the harness whose numbers mean nothing).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from bench._common import write_parquet
from bench._pipeline import QUALITY, TINY, growth_exponent, run_variant, settings

QUICK_FRAMES, QUICK_SIZES = (10, 20), ((48, 32), (96, 64))


def parse_sizes(text: str) -> list[tuple[int, int]]:
    out = []
    for part in text.split(","):
        try:
            w, h = (int(v) for v in part.strip().lower().split("x"))
        except ValueError:
            raise ValueError(f"--sizes: expected WxH values such as 320x180, got {part!r}") from None
        out.append((w, h))
    return out


def variants(frames: list[int], sizes: list[tuple[int, int]]) -> list[tuple[str, int, int, int]]:
    """(sweep, n_frames, width, height): the frame sweep at sizes[0], then the pixel sweep at frames[0]."""
    out = [("frames", n, *sizes[0]) for n in frames]
    out += [("pixels", frames[0], w, h) for w, h in sizes]
    return out


def run(frames: list[int], sizes: list[tuple[int, int]], quick: bool = False, force: bool = False,
        data_root: Path = Path("data"), out_dir: Path = Path("data/bench")) -> tuple[pd.DataFrame, pd.DataFrame]:
    rows = []
    for sweep, n, w, h in variants(frames, sizes):
        seq = f"synth_scale{'q' if quick else ''}_{n}f_{w}x{h}"
        knobs = {**(TINY if quick else {}), "synth.n_frames": n, "synth.width": w, "synth.height": h,
                 "synth.n_labelled": max(1, n // 40)}
        print(f"[bench scale] {seq}", file=sys.stderr)
        r = run_variant(seq, settings(knobs), data_root, force=force)
        force = False if (sweep, n, w, h) == ("frames", frames[0], *sizes[0]) else force  # shared point once
        for st in r.stages.itertuples(index=False):
            rows.append({"sweep": sweep, "seq": seq, "n_frames": n, "width": w, "height": h, "pixels": w * h,
                         "n_windows": max(1, n // 40), "stage": st.stage, "seconds": st.seconds,
                         "peak_rss_mb": st.peak_rss_mb, **r.quality})
    df = pd.DataFrame(rows)
    exps = []
    for (sweep, stage), g in df.groupby(["sweep", "stage"], sort=False):
        x = g.n_frames if sweep == "frames" else g.pixels
        exps.append({"sweep": sweep, "stage": stage, "time_exponent": growth_exponent(x, g.seconds),
                     "memory_exponent": growth_exponent(x, g.peak_rss_mb),
                     "seconds_max": float(g.seconds.max()), "peak_rss_mb_max": float(g.peak_rss_mb.max())})
    ex = pd.DataFrame(exps)
    tag = "scale_quick" if quick else "scale"
    write_parquet(df, out_dir / f"{tag}.parquet")
    write_parquet(ex, out_dir / f"{tag}_exponents.parquet")
    plot(df, ex, out_dir / f"{tag}.png")
    return df, ex


def plot(df: pd.DataFrame, ex: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    for col, (sweep, xcol, xlabel) in enumerate((("frames", "n_frames", "frames"), ("pixels", "pixels", "pixels"))):
        part = df[df.sweep == sweep]
        for row, (ycol, ylabel, ecol) in enumerate((("seconds", "stage wall time (s)", "time_exponent"),
                                                     ("peak_rss_mb", "peak memory, workers included (MiB)",
                                                      "memory_exponent"))):
            ax = axes[row, col]
            for stage, g in part.groupby("stage", sort=False):
                k = ex.loc[(ex.sweep == sweep) & (ex.stage == stage), ecol]
                label = f"{stage} (k={float(k.iloc[0]):.2f})" if len(k) else stage
                ax.loglog(g[xcol], g[ycol], "o-", label=label, ms=3)
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
            ax.legend(fontsize=6)
    q = df.drop_duplicates("seq")
    fig.suptitle("pag bench scale: " + "; ".join(f"{r.seq}: PSNR {r.psnr_db:.1f} PQ {r.pq:.2f} count err "
                                                  f"{r.count_error_rel:+.2f}" for r in q.itertuples()), fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench scale", description=__doc__.split("\n")[0])
    p.add_argument("--frames", default="60,120,240,480", help="frame counts of the frame sweep")
    p.add_argument("--sizes", default="320x180,640x360,1280x720", help="image sizes of the pixel sweep")
    p.add_argument("--quick", action="store_true", help=f"tiny smoke run: frames {QUICK_FRAMES}, sizes {QUICK_SIZES}")
    p.add_argument("--force", action="store_true", help="rerun every stage of every variant")
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    frames = list(QUICK_FRAMES) if a.quick else [int(v) for v in a.frames.split(",")]
    sizes = list(QUICK_SIZES) if a.quick else parse_sizes(a.sizes)
    if min(frames) < 3:
        raise ValueError(f"--frames must all be >= 3 (a labelled frame is never the first or last), got {frames}")
    df, ex = run(frames, sizes, a.quick, a.force, a.data_root, a.out)
    print(ex.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    cols = ["seq", *[c for c in ("psnr_db", "pq", "count_error_rel") if c in QUALITY]]
    print(df.drop_duplicates("seq")[cols].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print(f"wrote {a.out / ('scale_quick' if a.quick else 'scale')}.parquet, _exponents.parquet and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
