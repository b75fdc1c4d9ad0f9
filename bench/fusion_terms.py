"""Each cost term of the fusion checked on finished rows: the row fused with the term off beside the row fused
with every term on, counted and scored by the evaluate stage.

    pag bench fusion_terms [--seqs synth_rows_dense,...] [--quick] [--data-root data] [--out data/bench]
    pag bench fusion_terms --figure SEQ [--data-root data]      # docs/fusion_frame.png

`--figure SEQ` fuses the row once (in a temporary data/ as above) and draws its frame with the most fruits:
the render's labels, the detector's segments, the evidence (per pixel the margin between the best and the
second-best option's cost) and the fused ids, into docs/fusion_frame.png.

The terms are those of rowmap.fusion.assignment (render, detector, shape, surface, order; docs/fusion.md).
panoptic_fusion, fruit_count and evaluate run again, through the runner in a temporary data/ linked to the
row's (bench._common.run_stages: the NeRF is not refitted, the row's own outputs are not touched), each with the
row's resolved configuration and panoptic_fusion.terms_off naming one term. By default the rows are the
finished rows of `pag bench rows` (with --quick those of `pag bench rows --quick`, table fusion_terms_quick).

A term helps a row when switching it off lowers the row's score, compared in this order: row ID consistency,
then the F1 of the counted fruits, then PQ (the first that moves by more than TOLERANCE decides); it hurts the
row when the score rises. The verdict per term: 'keep' if it helps some row and hurts none, 'mixed' if it
helps some and hurts others, 'drop' if it hurts rows and helps none, 'no effect' if it changes nothing.
Writes <out>/fusion_terms.parquet (one row per sequence and variant, then one verdict row per term).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from bench._common import run_stages, write_parquet
from bench.count_rules import family_seqs, row_config, verdict
from pipeline.catalog import dataset
from rowmap.fusion import TERMS

STAGES = ("panoptic_fusion", "fruit_count", "evaluate")
"""The stages rerun per variant, in this order."""
SCORES = {"row_id": "id_consistency", "pq": "pq", "count_gt": "count_gt", "count_pred": "count_pred",
          "recall": "fruit_recall", "precision": "fruit_precision"}
"""table column -> row-scope metric of the evaluation table."""
ORDER = ("row_id", "f1", "pq")
"""The scores a verdict compares, the first that moves deciding."""
TOLERANCE = {"row_id": 1e-9, "f1": 1e-9, "pq": 1e-3}


def score_variant(data_root: Path, seq: str, off: tuple[str, ...]) -> dict[str, float]:
    """The three stages with panoptic_fusion.terms_off = `off` over the row's resolved settings; the row scores
    of the evaluation and the seconds panoptic_fusion ran."""
    config = row_config(data_root, seq, STAGES)
    config["panoptic_fusion"] = {**config["panoptic_fusion"], "terms_off": list(off)}
    out, results = run_stages(seq, data_root, list(STAGES), config=config)
    ev = out["evaluation"]
    row = ev[ev.scope == "row"].set_index("metric").value
    rec = {col: float(row.get(metric, np.nan)) for col, metric in SCORES.items()}
    p, r = rec["precision"], rec["recall"]
    rec["f1"] = 2 * p * r / (p + r) if p + r > 0 else float("nan")
    rec["fusion_s"] = float(results[0].seconds)
    return rec


def effect(base: pd.Series, off: pd.Series) -> int:
    """-1 when the term helps (the score falls with it off), +1 when it hurts, 0 for no change (ORDER)."""
    for col in ORDER:
        d = off[col] - base[col]
        if np.isfinite(d) and abs(d) > TOLERANCE[col]:
            return 1 if d > 0 else -1
    return 0


def verdicts(df: pd.DataFrame) -> pd.DataFrame:
    """Per term: the rows it helps, the rows it hurts and the verdict."""
    base = df[df.variant == "all terms"].set_index("seq")
    out = []
    for term in TERMS:
        off = df[df.variant == f"{term} off"].set_index("seq")
        signs = {seq: effect(base.loc[seq], off.loc[seq]) for seq in off.index if seq in base.index}
        helps = sorted(s for s, e in signs.items() if e < 0)
        hurts = sorted(s for s, e in signs.items() if e > 0)
        out.append({"seq": "", "variant": f"{term} off", "term": term, "helps": ",".join(helps),
                    "hurts": ",".join(hurts), "verdict": verdict(helps, hurts)})
    return pd.DataFrame(out)


def run(seqs: list[str], data_root: Path = Path("data"), out_dir: Path = Path("data/bench"),
        name: str = "fusion_terms") -> pd.DataFrame:
    rows = []
    for seq in seqs:
        if not dataset("renders").path(data_root, seq).is_file():
            raise FileNotFoundError(f"{seq}: no NeRF renders under {data_root}; run `pag all --seq {seq}` (or "
                                    f"`pag bench rows`) first")
        for variant, off in {"all terms": (), **{f"{t} off": (t,) for t in TERMS}}.items():
            print(f"[bench fusion_terms] {seq}: {variant}", file=sys.stderr)
            rows.append({"seq": seq, "variant": variant, "term": variant.removesuffix(" off"),
                         **score_variant(data_root, seq, off)})
    df = pd.DataFrame(rows)
    df = pd.concat([df, verdicts(df)], ignore_index=True)
    write_parquet(df, out_dir / f"{name}.parquet")
    return df


def figure(data_root: Path, seq: str, path: Path = Path("docs/fusion_frame.png")) -> Path:
    """docs/fusion.md's figure: the densest fused frame of `seq` (see the module docstring)."""
    from unittest import mock

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import rowmap.fusion.assignment as assignment
    from rowmap.fusion import cost, frame_evidence

    seen: dict[int, tuple] = {}

    def keep(frame, models, owners, cfg):
        out, ev, ids = fused_label(frame, models, owners, cfg)
        c = np.sort(cost(frame_evidence(frame, models, owners, cfg), cfg), axis=1)   # every option of every pixel
        seen[frame.frame_id] = (frame, ev, out, c[:, 1] - c[:, 0] if c.shape[1] > 1 else c[:, 0])
        return out, ev, ids

    fused_label = assignment.fused_label
    with mock.patch.object(assignment, "fused_label", keep):
        run_stages(seq, data_root, ["panoptic_fusion"], config={"panoptic_fusion": row_config(
            data_root, seq, STAGES)["panoptic_fusion"]})
    fid = max(seen, key=lambda f: len(np.unique(seen[f][2][seen[f][2] > 0])))
    frame, ev, fused, margin = seen[fid]
    evidence_img = np.full(frame.label.shape, np.nan)
    evidence_img.ravel()[ev.pixels] = margin
    seg = frame.segments if frame.segments is not None else np.zeros_like(frame.label)
    rng = np.random.default_rng(0)
    colours = rng.uniform(0.2, 1.0, (int(max(fused.max(), frame.label.max(), seg.max())) + 2, 3))
    colours[0] = 0.0

    def paint(lab: np.ndarray) -> np.ndarray:
        return colours[np.maximum(lab, 0)]

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.4))
    panels = [(paint(frame.label), "render: fruit ids (black: stuff)"), (paint(seg), "detector segments"),
              (evidence_img, "evidence: cost margin of the chosen option"), (paint(fused), "fused ids")]
    for ax, (img, title) in zip(axes, panels):
        im = ax.imshow(img, cmap="viridis" if img.ndim == 2 else None, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        if img.ndim == 2:
            fig.colorbar(im, ax=ax, fraction=0.03)
    fig.suptitle(f"{seq}, frame {fid}: {len(ev.ids)} candidate fruits", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench fusion_terms", description=__doc__.split("\n")[0])
    p.add_argument("--seqs", default="", help="comma-separated finished rows (default: the finished family rows)")
    p.add_argument("--quick", action="store_true", help="the rows of `pag bench rows --quick` (by default)")
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    p.add_argument("--figure", default="", metavar="SEQ", help="draw docs/fusion_frame.png from this row instead")
    a = p.parse_args(argv)
    if a.figure:
        print(f"wrote {figure(a.data_root, a.figure)}")
        return 0
    seqs = [s.strip() for s in a.seqs.split(",") if s.strip()] or family_seqs(a.out, a.quick)
    if not seqs:
        raise ValueError(f"no rows to check: give --seqs or run `pag bench rows` first (no finished row under {a.out})")
    name = "fusion_terms_quick" if a.quick else "fusion_terms"
    df = run(seqs, a.data_root, a.out, name)
    cols = ["seq", "variant", "row_id", "pq", "count_pred", "count_gt", "precision", "recall", "fusion_s"]
    print(df[df.seq != ""][cols].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print(df[df.seq == ""][["term", "helps", "hurts", "verdict"]].to_string(index=False))
    print(f"wrote {a.out / name}.parquet")
    return 0


if __name__ == "__main__":
    sys.exit(main())
