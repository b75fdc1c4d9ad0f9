

def test_staging_folders_of_dead_runs_are_cleaned_up(tmp_path):
    import subprocess
    import sys

    from pipeline import io

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    final = tmp_path / "nerf"
    stale = tmp_path / f".nerf.staging-{int(dead.stdout)}"
    (stale / "window_000").mkdir(parents=True)
    live = tmp_path / ".nerf.staging-1"          # pid 1 is alive: another run's folder stays
    live.mkdir()
    path = io.staging_dir(final)
    assert path.is_dir() and not stale.exists() and live.exists()
