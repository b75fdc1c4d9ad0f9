"""Peak memory of the process tree: a worker's allocation is seen, and the runner records it per stage."""
import json
import subprocess
import sys
import time

import pytest

from fake_stages import first, make, second
from pipeline.resources import PeakMemory, tree_rss_bytes
from pipeline.runner import Runner

CHILD = "import numpy as np, time; a = np.ones(300 * 2**20 // 8); time.sleep(1.5)"  # holds 300 MiB for 1.5 s


def test_peak_includes_a_child_process():
    base = tree_rss_bytes() / 2**20
    with PeakMemory(interval_s=0.05) as m:
        subprocess.run([sys.executable, "-c", CHILD], check=True)
    assert m.peak_mb - base > 250  # the child's 300 MiB, not only this process
    with PeakMemory(interval_s=0.05) as idle:
        time.sleep(0.2)
    assert idle.peak_mb < m.peak_mb - 250  # the child is gone: nothing left over


def test_bad_interval_is_refused():
    with pytest.raises(ValueError, match="interval_s must be > 0"):
        PeakMemory(interval_s=0)


def test_runner_records_seconds_and_peak_memory_per_stage(tmp_path):
    stages = [make("first", [], ["windows", "images"], first),
              make("second", ["windows", "images"], ["gt_segments"], second)]
    results = Runner("seqA", data_root=tmp_path, show_progress=False, stages=stages).run()
    for r in results:
        rec = json.loads((tmp_path / "interim" / "seqA" / "_manifest" / f"{r.stage}.json").read_text())
        assert rec["seconds"] >= 0 and rec["peak_rss_mb"] == pytest.approx(r.peak_rss_mb, abs=0.1)
        assert r.peak_rss_mb > 10  # at least this Python process
