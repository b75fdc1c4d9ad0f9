"""Numerical stress suite: the model pieces under extreme but possible inputs.

    pag bench stress [--size full|fast] [--device cpu] [--out data/bench]

The cases are the parametrised pytest cases of tests/stress/ (stress_cases.py, where each case says what it
feeds and checks); the test suite runs them at the fast size, this bench runs the same case functions at
either size and writes every check: data/bench/stress.parquet (case, component, passed, detail, size, device,
case_s); exit code 1 if any check fails.
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import pandas as pd

CASES_FILE = Path(__file__).resolve().parents[1] / "tests" / "stress" / "stress_cases.py"


def _load_cases():
    """tests/stress/stress_cases.py as a module (tests/ is not a package)."""
    if "stress_cases" in sys.modules:
        return sys.modules["stress_cases"]
    if not CASES_FILE.is_file():
        raise FileNotFoundError(f"the stress cases {CASES_FILE} are missing; `pag bench stress` runs from a checkout")
    spec = importlib.util.spec_from_file_location("stress_cases", CASES_FILE)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["stress_cases"] = mod
    spec.loader.exec_module(mod)
    return mod


_cases = _load_cases()
Check, Checks, SIZES = _cases.Check, _cases.Checks, _cases.SIZES
CASES = dict(_cases.CASES)


def run_case(name: str, n: int, device: str = "cpu") -> list:
    """One case; an exception escaping it is itself a failed check (the library crashed on the input)."""
    try:
        return list(CASES[name](n, device))
    except Exception as err:  # noqa: BLE001
        return [Check("case", False, f"crashed: {type(err).__name__}: {err}")]


def run(size: str = "full", device: str = "cpu", out_dir: Path | None = Path("data/bench")) -> pd.DataFrame:
    if size not in SIZES:
        raise ValueError(f"size must be one of {list(SIZES)}, got {size!r}")
    n = SIZES[size]
    rows = []
    for name in CASES:
        t0 = time.perf_counter()
        checks = run_case(name, n, device)
        dt = time.perf_counter() - t0
        rows += [{"case": name, "component": c.component, "passed": c.passed, "detail": c.detail, "size": n,
                  "device": device, "case_s": dt} for c in checks]
    df = pd.DataFrame(rows)
    if out_dir is not None:
        from bench._common import write_parquet

        out_dir.mkdir(parents=True, exist_ok=True)
        write_parquet(df, out_dir / "stress.parquet")
    return df


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench stress", description=__doc__.split("\n")[0])
    p.add_argument("--size", choices=list(SIZES), default="full", help="points / rays per case")
    p.add_argument("--device", default="cpu", help="torch device ('cpu', 'cuda')")
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    df = run(a.size, a.device, a.out)
    for case, part in df.groupby("case", sort=False):
        bad = part[~part.passed]
        print(f"{'PASS' if bad.empty else 'FAIL'}  {case:28s} {len(part) - len(bad)}/{len(part)} checks "
              f"({part.case_s.iloc[0]:.1f} s)")
        for _, r in bad.iterrows():
            print(f"      {r.component}: {r.detail}")
    print(f"\n{int(df.passed.sum())}/{len(df)} checks passed; table: {a.out / 'stress.parquet'}")
    return 0 if df.passed.all() else 1
