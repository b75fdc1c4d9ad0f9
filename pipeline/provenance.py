"""Which code produced an output and what it cost: the git commit of the project tree (recorded beside tables
and benches) and the runner's per-stage manifest records (wall time, peak memory)."""
from __future__ import annotations

import functools
import json
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd

REPO_ROOT = Path(__file__).resolve().parents[1]


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """Short commit hash of the project checkout, with "+dirty" when tracked files differ from it;
    "unknown" outside a git checkout (an installed copy, a tarball)."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(REPO_ROOT), *args], capture_output=True, text=True,
                              timeout=20, check=True).stdout.strip()
    try:
        commit = git("rev-parse", "--short=10", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return commit + ("+dirty" if dirty else "")


def stage_costs(data_root: Path, seq: str, stages: list[str]) -> pd.DataFrame:
    """Per stage the wall time (s), the peak resident memory of the process tree (MiB, workers included)
    and the commit of the run that produced the stage's current outputs, from the runner's manifest
    records (NaN / '' where a stage has no record, e.g. it has not run or was skipped for this row)."""
    rows = []
    for name in stages:
        path = Path(data_root) / "interim" / seq / "_manifest" / f"{name}.json"
        try:
            rec = json.loads(path.read_text()) if path.is_file() else {}
        except (OSError, ValueError):
            rec = {}
        rows.append({"stage": name, "seconds": float(rec.get("seconds", np.nan)),
                     "peak_rss_mb": float(rec.get("peak_rss_mb", np.nan)), "code_version": rec.get("code_version", "")})
    return pd.DataFrame(rows, columns=["stage", "seconds", "peak_rss_mb", "code_version"])
