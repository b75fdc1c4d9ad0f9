"""scripts/compare_runs.py: two runs' tables are equal within tolerance, or the difference is reported."""
import importlib.util
from pathlib import Path

import pandas as pd

spec = importlib.util.spec_from_file_location("compare_runs", Path(__file__).parents[2] / "scripts" / "compare_runs.py")
compare_runs = importlib.util.module_from_spec(spec)
spec.loader.exec_module(compare_runs)


def write(root: Path, name: str, df: pd.DataFrame) -> None:
    (root / "processed" / "s").mkdir(parents=True, exist_ok=True)
    df.to_parquet(root / "processed" / "s" / f"{name}.parquet")


def test_equal_within_tolerance_new_tables_listed_and_real_differences_fail(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    t = pd.DataFrame({"metric": ["pq", "miou"], "value": [0.5, 0.25], "fit_s": [1.0, 2.0]})
    write(a, "evaluation", t)
    write(b, "evaluation", t.assign(value=t.value + 1e-9, fit_s=[9.0, 9.0]))   # noise and timings
    write(b, "renders", pd.DataFrame({"kind": ["rgb"]}))                        # a new output
    assert compare_runs.main([str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "only in after: processed/s/renders.parquet" in out and "EQUAL" in out
    write(b, "evaluation", t.assign(value=[0.5, 0.3]))
    assert compare_runs.main([str(a), str(b)]) == 1
    assert "evaluation.parquet: DIFFERENT" in capsys.readouterr().out
