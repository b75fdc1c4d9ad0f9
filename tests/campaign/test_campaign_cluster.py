"""Scale-out, shown: a real `dask scheduler` and two `dask worker` processes started from the command line, a
two-row campaign run on them with --scheduler; both workers fit windows and the outputs equal a local run's."""
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from campaign_fixture import SEQS, TABLES, campaign_args, read_partitioned
from pipeline import cli

ROOT = Path(__file__).resolve().parents[2]
DASK = Path(sys.executable).parent / "dask"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_workers(address: str, names: set[str], procs: list[subprocess.Popen], timeout_s: float = 120) -> None:
    from distributed import Client

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        dead = [p.args for p in procs if p.poll() is not None]
        if dead:
            raise RuntimeError(f"dask processes exited early: {dead}")
        try:
            with Client(address, timeout="5s") as client:
                got = {str(w["name"]) for w in client.scheduler_info()["workers"].values()}
                if names <= got:
                    return
        except OSError:
            pass
        time.sleep(1)
    raise TimeoutError(f"workers {sorted(names)} did not register with {address} in {timeout_s} s")


@pytest.mark.slow
@pytest.mark.skipif(not DASK.is_file(), reason=f"no dask command line at {DASK}")
def test_two_command_line_workers_share_the_windows_and_match_a_local_run(local_campaign, tmp_path):
    local_root, config = local_campaign
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}  # the workers import this checkout's stages and nerf
    common = ["--no-dashboard"]
    procs: list[subprocess.Popen] = []
    try:
        procs.append(subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", str(port), *common],
                                      env=env, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        for name in ("worker-a", "worker-b"):
            procs.append(subprocess.Popen(
                [str(DASK), "worker", address, "--nthreads", "1", "--nworkers", "1", "--name", name,
                 "--host", "127.0.0.1", *common], env=env, cwd=tmp_path,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        wait_for_workers(address, {"worker-a", "worker-b"}, procs)
        root = tmp_path / "data"
        assert cli.main(campaign_args(root, config, "--scheduler", address)) == 0
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    wm = pd.concat([pd.read_parquet(root / "processed" / seq / "window_metrics.parquet") for seq in SEQS])
    assert len(wm) == 4 and set(wm.worker) == {"worker-a", "worker-b"}, wm[["window_id", "worker"]]
    for table in TABLES:
        pd.testing.assert_frame_equal(read_partitioned(root, table), read_partitioned(local_root, table),
                                      check_exact=False, rtol=1e-6, obj=table)
    rows = pd.read_parquet(root / "processed" / "_campaign" / "rows.parquet").drop(columns="report_path")
    local_rows = pd.read_parquet(local_root / "processed" / "_campaign" / "rows.parquet").drop(columns="report_path")
    pd.testing.assert_frame_equal(rows, local_rows, check_exact=False, rtol=1e-6)
