"""Bad input around the data folder, through the CLI as a user runs it: a sequence path with spaces and
non-ASCII characters, a read-only data/ folder, a file where a folder should be, a full disk."""
import errno
import os
import stat
from pathlib import Path

import cv2
import pandas as pd
import pytest

from pipeline import cli

TINY = ["--no-progress", "--set", "synth.n_frames=6", "--set", "synth.width=48", "--set", "synth.height=32",
        "--set", "synth.n_labelled=1", "--set", "synth.supersample=1", "--set", "synth.workers=1",
        "--set", "synth.write_bag=false"]


def pag(*args) -> int:
    return cli.main([*args, *TINY])


def test_bad_input_sequence_path_with_spaces_and_non_ascii_characters(tmp_path):
    root = tmp_path / "dätä földer" / "data"
    seq = "synth row ü 1"
    assert pag("all", "--seq", seq, "--data-root", str(root), "--to", "windows") == 0
    frames = pd.read_parquet(root / "interim" / seq / "frames.parquet")
    assert len(frames) == 6 and pd.read_parquet(root / "interim" / seq / "windows.parquet").window_id.nunique() >= 1
    for p in [*frames.rgb_path, *frames.depth_path, *frames.det_instance_path.dropna()]:
        assert seq in p and cv2.imread(str(root / p), cv2.IMREAD_UNCHANGED) is not None


@pytest.fixture
def synth_root(tmp_path) -> Path:
    root = tmp_path / "data"
    assert pag("synth", "--seq", "synth_t", "--data-root", str(root)) == 0
    return root


def test_bad_input_read_only_data_folder_is_an_error_naming_it(synth_root, capsys):
    mode = synth_root.stat().st_mode
    os.chmod(synth_root, stat.S_IRUSR | stat.S_IXUSR)
    try:
        if os.access(synth_root, os.W_OK):
            pytest.skip("running as root: a read-only folder is still writable")
        assert pag("ingest", "--seq", "synth_t", "--data-root", str(synth_root)) == 2
    finally:
        os.chmod(synth_root, mode)
    err = capsys.readouterr().err
    assert f"the folder {synth_root} is read-only or not writable by this user" in err and "cannot write" in err


def test_bad_input_read_only_file_system_is_an_error_naming_it(synth_root, capsys, monkeypatch):
    """data/ on a read-only mount: every open for writing fails with EROFS, for root too (unlike the chmod
    case above), and the run stops with the same one-paragraph error naming the folder."""
    real_open = os.open
    interim = str(synth_root / "interim")

    def read_only_open(path, flags, *args, **kwargs):
        if str(path).startswith(interim) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", read_only_open)
    assert pag("ingest", "--seq", "synth_t", "--data-root", str(synth_root)) == 2
    err = capsys.readouterr().err
    assert "read-only or not writable by this user" in err and "cannot write" in err
    assert str(synth_root / "interim" / "synth_t") in err


def test_bad_input_data_folder_with_a_file_in_the_way_is_an_error_naming_it(synth_root, capsys):
    import shutil
    shutil.rmtree(synth_root / "interim")
    (synth_root / "interim").write_text("not a folder")
    assert pag("ingest", "--seq", "synth_t", "--data-root", str(synth_root)) == 2
    err = capsys.readouterr().err
    # the first thing a run writes under interim/ is the row lock; the error names it and the file in the way
    assert f"{synth_root / 'interim'} is a file, not a folder" in err and "_manifest/lock" in err


def no_output_left(root: Path) -> None:
    interim = root / "interim" / "synth_t"
    leftovers = [p.name for p in interim.iterdir() if p.name not in ("config.resolved.yaml", "_manifest")]
    assert leftovers == [], leftovers
    assert not (interim / "_manifest" / "ingest.json").exists()


def test_bad_input_full_disk_while_writing_a_table_names_it_and_leaves_no_partial_output(synth_root, capsys,
                                                                                           monkeypatch):
    real_fsync = os.fsync

    def fsync(fd):
        if "frames.parquet" in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    if not Path("/proc/self/fd").is_dir():
        pytest.skip("needs /proc to tell which file is written")
    monkeypatch.setattr(os, "fsync", fsync)
    assert pag("ingest", "--seq", "synth_t", "--data-root", str(synth_root)) == 2
    err = capsys.readouterr().err
    assert f"cannot write {synth_root / 'interim' / 'synth_t' / 'frames.parquet'}: the disk is full" in err
    no_output_left(synth_root)


def test_bad_input_full_disk_while_writing_images_names_the_file(synth_root, capsys, monkeypatch):
    import shutil
    from collections import namedtuple

    real_imwrite = cv2.imwrite
    monkeypatch.setattr(cv2, "imwrite", lambda p, img, *a: False if "images.staging" in str(p) else real_imwrite(p, img, *a))
    monkeypatch.setattr(shutil, "disk_usage", lambda p: namedtuple("usage", "total used free")(10**9, 10**9, 0))
    assert pag("ingest", "--seq", "synth_t", "--data-root", str(synth_root)) == 2
    err = capsys.readouterr().err
    assert "cannot write" in err and "rgb/1600000000000000000.png: the disk is full" in err
    no_output_left(synth_root)
