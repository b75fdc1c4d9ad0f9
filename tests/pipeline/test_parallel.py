import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import parallel

ROOT = Path(__file__).resolve().parents[2]


def square_or_fail(x):
    parallel.report(str(x), 1, 1, value=float(x))
    if x == 3:
        raise FloatingPointError("non-finite loss at step 7")
    return x * x


@pytest.mark.slow
def test_map_tasks_runs_all_and_keeps_failures_separate():
    out = parallel.map_tasks(square_or_fail, {str(i): i for i in range(4)}, n_workers=2, show_progress=False)
    assert {k: o.result for k, o in out.items() if o.error is None} == {"0": 0, "1": 1, "2": 4}
    assert isinstance(out["3"].error, FloatingPointError) and "step 7" in str(out["3"].error)


def env_of_task(_):
    import os

    return os.environ.get("MALLOC_TRIM_THRESHOLD_")


@pytest.mark.slow
def test_local_workers_do_not_get_dask_malloc_trim_setting():
    out = parallel.map_tasks(env_of_task, {"a": 0}, n_workers=1, show_progress=False)
    assert out["a"].error is None and out["a"].result is None


FAULTS_SCRIPT = """
import resource, sys
import numpy as np
from pipeline.parallel import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
np.ones(1 << 18)  # first 2 MiB allocation: faults either way (below numpy's 4 MiB huge-page size)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    np.ones(1 << 18)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc settings")
def test_keep_freed_memory_stops_page_faults_on_every_large_allocation():
    # a process started like a Dask worker (MALLOC_TRIM_THRESHOLD_ set): every 2 MiB array is mmap'ed anew
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    faults = {mode: int(subprocess.run([sys.executable, "-c", FAULTS_SCRIPT, mode], env=env, check=True,
                                       capture_output=True, text=True, cwd=ROOT).stdout)
              for mode in ("plain", "keep")}
    # plain: every allocation faults its pages in again (20 x 512 faults with 4 KiB pages; fewer where the
    # kernel backs anonymous memory with larger folios, e.g. 20 x 128 with 16 KiB ones); keep: reused, ~none
    assert faults["plain"] >= 20
    assert faults["keep"] < faults["plain"] // 10


def name_of_worker(_):
    return parallel.worker_name()


@pytest.mark.slow
def test_map_tasks_from_several_threads_share_one_cluster(monkeypatch):
    import threading

    opened = []
    real = parallel.client_for

    def counting(*args):
        opened.append(args)
        return real(*args)

    monkeypatch.setattr(parallel, "client_for", counting)
    results = {}

    def submit(name):
        results[name] = parallel.map_tasks(name_of_worker, {"a": 0, "b": 1}, show_progress=False)

    with parallel.shared_cluster(None, 2, 1):
        threads = [threading.Thread(target=submit, args=(n,)) for n in ("row1", "row2")]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert opened == [(None, 2, 1)]
    workers = {o.worker for out in results.values() for o in out.values()}
    assert all(o.error is None and o.result == o.worker for out in results.values() for o in out.values())
    assert workers <= {"0", "1"} and workers
    assert parallel.task_threads(0, 4) == max(1, (os.cpu_count() or 1) // 4)  # the block is closed


def test_idle_slots_are_shared_only_once_the_queue_no_longer_fills_the_workers():
    assert parallel.idle_slots(n_workers=2, unfinished=3) == 0  # queued tasks will take the free worker
    assert parallel.idle_slots(n_workers=2, unfinished=2) == 0
    assert parallel.idle_slots(n_workers=2, unfinished=1) == 1  # the last window takes the other core
    assert parallel.idle_slots(n_workers=4, unfinished=2) == 1
    assert parallel.idle_slots(n_workers=5, unfinished=2) == 1  # rounded down: never more threads than cores
    assert parallel.idle_slots(n_workers=4, unfinished=0) == 0


def short_or_long(kind):
    """'short' returns at once; 'long' reports progress until it has more torch threads (or 12 s pass: six
    looks at the idle slots)."""
    import time

    import torch

    if kind == "short":
        return torch.get_num_threads()
    t0 = time.monotonic()
    while torch.get_num_threads() < 2 and time.monotonic() - t0 < 12:
        parallel.report("long", 0, 1)
        time.sleep(0.2)
    return torch.get_num_threads()


@pytest.mark.slow
def test_the_last_task_takes_the_threads_of_a_finished_worker():
    out = parallel.map_tasks(short_or_long, {"short": "short", "long": "long"}, n_workers=2, threads_per_worker=1,
                             show_progress=False, idle_threads=True)
    assert out["short"].result == 1 and out["short"].threads == 1
    assert out["long"].result == 2 and out["long"].threads == 2
    kept = parallel.map_tasks(short_or_long, {"short": "short", "long": "long"}, n_workers=2, threads_per_worker=1,
                              show_progress=False, idle_threads=False)
    assert kept["long"].result == 1 and kept["long"].seconds > 11  # nobody gave it the idle core


def first_part(x):
    """Sleeps a little (task 0 longest) and says when it started and ended."""
    import time

    t0 = time.time()
    if x == 9:
        raise ValueError("the first part of task 9 failed")
    time.sleep(4.0 if x == 0 else 0.5)
    return {"x": x, "first": (t0, time.time())}


def second_part(r):
    import time

    return {**r, "second": time.time(), "value": r["x"] * 10}


@pytest.mark.slow
def test_second_parts_run_as_tasks_of_their_own_after_every_first_part():
    out = parallel.map_tasks(first_part, {str(i): i for i in (0, 1, 2, 3)}, n_workers=2, threads_per_worker=1,
                             show_progress=False, then=second_part)
    done = {k: o.result for k, o in out.items()}
    assert {k: r["value"] for k, r in done.items()} == {"0": 0, "1": 10, "2": 20, "3": 30}
    last_first_start = max(r["first"][0] for r in done.values())
    assert all(r["second"] >= last_first_start for r in done.values())   # every first part before a second
    # 2's and 3's first parts ran beside 0's, as soon as 1's had finished; then 1's second part
    assert done["3"]["first"][0] < done["0"]["first"][1] and done["1"]["second"] < done["0"]["first"][1]
    assert out["0"].seconds > out["1"].seconds >= 0.45   # a task's seconds: both parts'
    failed = parallel.map_tasks(first_part, {"9": 9, "1": 1}, n_workers=1, show_progress=False, then=second_part)
    assert isinstance(failed["9"].error, ValueError) and failed["9"].result is None   # no second part
    assert failed["1"].result["value"] == 10
