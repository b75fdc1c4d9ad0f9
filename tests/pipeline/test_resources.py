"""Peak memory of the process tree: a worker's allocation is seen, and the runner records it per stage."""
import json
import subprocess
import sys
import time

import pytest

from fake_stages import first, make, second
from pipeline.resources import PeakMemory, own_peak_mb, reset_own_peak, tree_rss_bytes
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


OWN_PEAK = """
import numpy as np
from pipeline.resources import own_peak_mb, reset_own_peak
a = np.ones(400 * 2**20 // 8)  # 400 MiB touched
del a
assert reset_own_peak()
before = own_peak_mb()
b = np.ones(200 * 2**20 // 8)
del b
print(before, own_peak_mb())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the kernel's high-water mark")
def test_own_peak_forgets_work_before_the_reset_and_sees_work_after():
    out = subprocess.run([sys.executable, "-c", OWN_PEAK], check=True, capture_output=True, text=True)
    before, after = map(float, out.stdout.split())
    assert before < 300  # the 400 MiB array before the reset is forgotten
    assert after - before > 180  # the 200 MiB one after it is seen, though freed again


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
