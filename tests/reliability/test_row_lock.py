"""One run per row: a second `pag` on a row that a live run holds is refused with the holder's pid; a lock
left by a killed run does not stick; read-only commands take no lock."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.lock import RowLock, RowLocked

REPO = Path(__file__).resolve().parents[2]
SEQ = "synth_lock"
SYNTH = ["--set", "synth.n_frames=6", "--set", "synth.width=48", "--set", "synth.height=32",
         "--set", "synth.n_labelled=1", "--set", "synth.supersample=1", "--set", "synth.workers=1",
         "--set", "run.progress_interval_s=0"]


def held_run(root: Path) -> subprocess.Popen:
    """`pag synth` in its own process group, holding (PAG_HOLD_AT) in the middle of the stage."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
               PAG_HOLD_AT="synth: render and write 2/")
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "synth", "--seq", SEQ, "--data-root", str(root),
                             *SYNTH], cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    watchdog = threading.Timer(120, lambda: os.killpg(proc.pid, signal.SIGKILL))
    watchdog.start()
    try:
        for line in proc.stderr:
            if "holding at" in line:
                return proc
    finally:
        watchdog.cancel()
    raise AssertionError(f"the held run ended with {proc.wait()} before holding")


def test_second_run_is_refused_while_one_runs_and_a_killed_runs_lock_is_taken_over(tmp_path, capsys):
    root = tmp_path / "data"
    first = held_run(root)
    try:
        assert cli.main(["synth", "--seq", SEQ, "--data-root", str(root), *SYNTH]) == 2
        err = capsys.readouterr().err
        assert f"row {SEQ} is being processed by pid {first.pid} (started 20" in err
        assert "Traceback" not in err
        # reading commands do not wait for the lock
        assert cli.main(["config", "--seq", SEQ, "--data-root", str(root)]) == 0
        assert cli.main(["stages"]) == 0 and cli.main(["schema", "frames"]) == 0
    finally:
        os.killpg(first.pid, signal.SIGKILL)
        first.wait()
        first.stderr.close()
    # the killed run's lock file (its pid inside) is still there; the kernel released its flock
    assert str(first.pid) in (root / "interim" / SEQ / "_manifest" / "lock").read_text()
    capsys.readouterr()
    assert cli.main(["synth", "--seq", SEQ, "--data-root", str(root), *SYNTH]) == 0
    err = capsys.readouterr().err
    assert "[pag] synth: done" in err and "being processed" not in err
    assert not list(root.glob(f"raw/.{SEQ}.staging-*")), "the killed run's staging folder is removed"


def test_lock_is_exclusive_between_holders_and_reentrant_within_one(tmp_path):
    a = RowLock(tmp_path, "row1")
    with a:
        with a:  # Runner.run inside Runner.run
            pass
        with pytest.raises(RowLocked, match=rf"row row1 is being processed by pid {os.getpid()} \(started "):
            RowLock(tmp_path, "row1").acquire()
        with RowLock(tmp_path, "row2"):  # other rows are independent
            pass
    with RowLock(tmp_path, "row1"):  # released on exit
        pass
