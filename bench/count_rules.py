"""Each counting rule of fruit_count checked on finished rows: the row counted with the rule off beside the
row counted with every rule on, scored by the evaluate stage.

    pag bench count_rules [--seqs synth_rows_dense,...] [--quick] [--data-root data] [--out data/bench]

The rules (fruit_count settings) are those that decide `counted`: fragments (min_count_frames,
min_count_points, with the lone_fragment_m exemption), unconfirmed fruits (detector_alpha), the far row
(max_depth_m), fruits wider than any fruit of the crop (max_count_diameter_m), one fruit under two ids
(duplicate_within_m) and the fruits the detector alone tracks at a recording's ends (end_tracks). Only fruit_count and
evaluate run again, through the runner in a temporary data/ linked to the row's, on the row's fused panoptic
frames as they are on disk (the NeRF is not refitted, and the row's own tables are not touched), each with
the row's resolved configuration and one rule switched off. By default the rows are the finished rows of
`pag bench rows` (data/bench/rows/*.json; with --quick those of `pag bench rows --quick`, and the table is
count_rules_quick.parquet).

A rule helps a row when switching it off lowers the F1 of the counted fruits (harmonic mean of precision
and recall, fruits matched to ground truth by 3D position) and hurts it when switching it off raises it.
The verdict per rule: 'keep' if it hurts no row, 'mixed' if it helps some rows and hurts others, 'no effect'
if it changes nothing. Writes <out>/count_rules.parquet (one row per sequence and variant, then one
verdict row per rule).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from bench._common import run_stages, write_parquet
from pipeline import dag
from pipeline.catalog import dataset

RULES_OFF: dict[str, dict[str, object]] = {
    "fragments": {"min_count_frames": 1, "min_count_points": 0},
    "unconfirmed": {"detector_alpha": 0.0},
    "far_row": {"max_depth_m": 1e6},
    "oversize": {"max_count_diameter_m": 1e6},
    "duplicates": {"duplicate_within_m": 0.0},
    "end_tracks": {"end_tracks": False},
}
"""Per rule, the fruit_count settings that switch it off."""
SCORES = {"count_gt": "count_gt", "count_pred": "count_pred", "count_error_rel": "count_error_rel",
          "recall": "fruit_recall", "precision": "fruit_precision"}
"""table column -> row-scope metric of the evaluation table."""
TOLERANCE = 1e-9
STAGES = ("fruit_count", "evaluate")
"""The stages rerun per variant, in this order."""


def row_config(data_root: Path, seq: str, stages: tuple[str, ...] = STAGES) -> dict[str, dict]:
    """The settings of `stages` as the row last ran them (its config.resolved.yaml), per stage; settings the
    stage no longer has are left out, and a stage the file lacks keeps its defaults."""
    path = data_root / "processed" / seq / "config.resolved.yaml"
    resolved = (yaml.safe_load(path.read_text()) or {}) if path.is_file() else {}
    out = {}
    for name in stages:
        names = {f.name for f in dataclasses.fields(dag.load_stage(name).config_class)}
        out[name] = {k: v for k, v in (resolved.get(name) or {}).items() if k in names}
    return out


def score_variant(data_root: Path, seq: str, off: dict[str, object]) -> dict[str, float]:
    """fruit_count with the settings `off` over the row's resolved ones, then evaluate, through the runner in a
    temporary data/ linked to the row's (bench._common.run_stages: the row's own outputs are not touched); the
    row scores of the evaluation."""
    config = row_config(data_root, seq)
    config["fruit_count"] = {**config["fruit_count"], **off}
    ev = run_stages(seq, data_root, list(STAGES), config=config)[0]["evaluation"]
    row = ev[ev.scope == "row"].set_index("metric").value
    out = {col: float(row.get(metric, np.nan)) for col, metric in SCORES.items()}
    p, r = out["precision"], out["recall"]
    out["f1"] = 2 * p * r / (p + r) if p + r > 0 else float("nan")
    return out


def verdict(helps: list[str], hurts: list[str]) -> str:
    """'mixed' if a piece helps some rows and hurts others, 'keep' if it only helps, 'drop' if it only hurts,
    'no effect' if neither (also the verdict of `pag bench fusion_terms`)."""
    return "mixed" if helps and hurts else "keep" if helps else "drop" if hurts else "no effect"


def verdicts(df: pd.DataFrame) -> pd.DataFrame:
    """Per rule: rows it helps (F1 falls with it off), rows it hurts (F1 rises) and the verdict."""
    base = df[df.variant == "all rules"].set_index("seq").f1
    out = []
    for rule in RULES_OFF:
        off = df[df.variant == f"{rule} off"].set_index("seq").f1
        delta = (off - base.reindex(off.index)).dropna()
        helps = sorted(delta.index[delta < -TOLERANCE])
        hurts = sorted(delta.index[delta > TOLERANCE])
        out.append({"seq": "", "variant": f"{rule} off", "rule": rule, "helps": ",".join(helps),
                    "hurts": ",".join(hurts), "verdict": verdict(helps, hurts)})
    return pd.DataFrame(out)


def run(seqs: list[str], data_root: Path = Path("data"), out_dir: Path = Path("data/bench"),
        name: str = "count_rules") -> pd.DataFrame:
    rows = []
    for seq in seqs:
        if not dataset("panoptic_frames").path(data_root, seq).is_file():
            raise FileNotFoundError(f"{seq}: no fused panoptic frames under {data_root}; run `pag all --seq {seq}` "
                                    f"(or `pag bench rows`) first")
        for variant, off in {"all rules": {}, **{f"{r} off": v for r, v in RULES_OFF.items()}}.items():
            print(f"[bench count_rules] {seq}: {variant}", file=sys.stderr)
            rows.append({"seq": seq, "variant": variant, "rule": variant.removesuffix(" off"),
                         **score_variant(data_root, seq, off)})
    df = pd.DataFrame(rows)
    df = pd.concat([df, verdicts(df)], ignore_index=True)
    write_parquet(df, out_dir / f"{name}.parquet")
    return df


def family_seqs(out_dir: Path, quick: bool = False) -> list[str]:
    """The sequences of the finished `pag bench rows` rows (`--quick`: of its smoke run), in file-name order."""
    done = out_dir / ("rows_quick" if quick else "rows")
    return [json.loads(p.read_text())["seq"] for p in sorted(done.glob("*.json"))]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench count_rules", description=__doc__.split("\n")[0])
    p.add_argument("--seqs", default="", help="comma-separated finished rows (default: the finished family rows)")
    p.add_argument("--quick", action="store_true", help="the rows of `pag bench rows --quick` (by default)")
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    seqs = [s.strip() for s in a.seqs.split(",") if s.strip()] or family_seqs(a.out, a.quick)
    if not seqs:
        raise ValueError("no rows to check: give --seqs or run `pag bench rows` first (no finished row under "
                         f"{a.out})")
    name = "count_rules_quick" if a.quick else "count_rules"
    df = run(seqs, a.data_root, a.out, name)
    cols = ["seq", "variant", "count_pred", "count_gt", "count_error_rel", "recall", "precision", "f1"]
    print(df[df.seq != ""][cols].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print(df[df.seq == ""][["rule", "helps", "hurts", "verdict"]].to_string(index=False))
    print(f"wrote {a.out / name}.parquet")
    return 0


if __name__ == "__main__":
    sys.exit(main())
