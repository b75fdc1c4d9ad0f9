"""Compare the outputs of two pipeline runs: every Parquet table and PNG under two data/ folders.

    python scripts/compare_runs.py BEFORE/data AFTER/data [--rtol 1e-6] [--atol 1e-5] [--ignore fit_s ...]

Tables are equal when they have the same columns and rows and their values agree within the tolerances
(floats: |a - b| <= atol + rtol |b|; everything else exactly); PNGs when their bytes are equal. Timing
columns (fit_s, render_s_per_image, panoptic_fit_s, threads) are left out by default: they differ between
any two runs. A table or image present in only one run is listed, not a failure (a new output). Exit code 0
when everything both runs have is equal, 1 otherwise.
"""
from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import numpy as np
import pandas as pd

TIMING_COLUMNS = ("fit_s", "render_s_per_image", "panoptic_fit_s", "threads")


def compare_table(a: pd.DataFrame, b: pd.DataFrame, rtol: float, atol: float, ignore: tuple[str, ...]) -> str:
    """'' when equal, else why not."""
    if list(a.columns) != list(b.columns):
        return f"columns differ: {list(a.columns)} vs {list(b.columns)}"
    if len(a) != len(b):
        return f"{len(a)} vs {len(b)} rows"
    cols = [c for c in a.columns if c not in ignore]
    try:
        pd.testing.assert_frame_equal(a[cols], b[cols], check_exact=False, rtol=rtol, atol=atol)
    except AssertionError as err:
        return str(err).strip().splitlines()[0] + " " + " ".join(str(err).split())[-300:]
    return ""


def max_float_diff(a: pd.DataFrame, b: pd.DataFrame, ignore: tuple[str, ...]) -> float:
    diffs = [float(np.nanmax(np.abs(a[c].to_numpy(float) - b[c].to_numpy(float)), initial=0.0))
             for c in a.columns if c not in ignore and pd.api.types.is_float_dtype(a[c]) and len(a)]
    return max(diffs, default=0.0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("before", type=Path)
    p.add_argument("after", type=Path)
    p.add_argument("--rtol", type=float, default=1e-6)
    p.add_argument("--atol", type=float, default=1e-5)
    p.add_argument("--ignore", nargs="*", default=list(TIMING_COLUMNS), help="columns left out of the comparison")
    a = p.parse_args(argv)
    for root in (a.before, a.after):
        if not root.is_dir():
            print(f"error: {root} is not a folder", file=sys.stderr)
            return 2
    ignore = tuple(a.ignore)
    ok = True
    tables = {q.relative_to(a.before) for q in a.before.rglob("*.parquet")}
    tables_after = {q.relative_to(a.after) for q in a.after.rglob("*.parquet")}
    for rel in sorted(tables ^ tables_after):
        print(f"only in {'before' if rel in tables else 'after'}: {rel}")
    for rel in sorted(tables & tables_after):
        x, y = pd.read_parquet(a.before / rel), pd.read_parquet(a.after / rel)
        why = compare_table(x, y, a.rtol, a.atol, ignore)
        ok &= not why
        print(f"{rel}: " + (f"DIFFERENT: {why}" if why else
                            f"equal ({len(x)} rows, max float difference {max_float_diff(x, y, ignore):.2e})"))
    digest = lambda q: hashlib.blake2b(q.read_bytes(), digest_size=16).hexdigest()  # noqa: E731
    pngs = {q.relative_to(a.before): q for q in a.before.rglob("*.png")}
    pngs_after = {q.relative_to(a.after): q for q in a.after.rglob("*.png")}
    differ = sorted(str(r) for r in pngs.keys() & pngs_after.keys() if digest(pngs[r]) != digest(pngs_after[r]))
    only = len(pngs.keys() ^ pngs_after.keys())
    ok &= not differ
    print(f"PNG: {len(pngs.keys() & pngs_after.keys())} in both, {len(differ)} differ {differ[:5]}, "
          f"{only} in one run only")
    print("EQUAL" if ok else "NOT EQUAL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
