import pandas as pd
import pyarrow.parquet as pq
import pytest

import fake_stages
from fake_stages import first, make, second
from pipeline import io
from pipeline.runner import PipelineError, Runner


def stages():
    return [make("first", [], ["windows", "images"], first), make("second", ["windows", "images"], ["gt_segments"], second)]


def runner(tmp_path, *overrides):
    return Runner("seqA", data_root=tmp_path, overrides=list(overrides), show_progress=False, stages=stages())


def run_all(tmp_path, *overrides, force=False):
    fake_stages.CALLS.clear()
    r = runner(tmp_path, *overrides)
    return [x.status for x in r.run(force=force)], list(fake_stages.CALLS)


def test_first_run_writes_validated_tables_dirs_and_config(tmp_path):
    statuses, calls = run_all(tmp_path)
    assert statuses == ["ran", "ran"] and calls == ["first", "second"]
    gt = pd.read_parquet(tmp_path / "processed" / "seqA" / "gt_segments.parquet") \
        if (tmp_path / "processed" / "seqA" / "gt_segments.parquet").exists() else \
        pd.read_parquet(tmp_path / "interim" / "seqA" / "gt_segments.parquet")
    assert gt["instance_id"].tolist() == [1, 1, 1]
    assert (tmp_path / "interim" / "seqA" / "images" / "a.txt").read_text() == "1"
    assert (tmp_path / "processed" / "seqA" / "config.resolved.yaml").is_file()
    meta = pq.read_schema(tmp_path / "interim" / "seqA" / "windows.parquet").metadata
    assert meta[b"pag.stage"] == b"first"


def test_unchanged_run_skips_and_config_change_reruns_only_what_it_affects(tmp_path):
    run_all(tmp_path)
    assert run_all(tmp_path) == (["skipped", "skipped"], [])
    # A change to `second`'s config reruns second only.
    assert run_all(tmp_path, "second.value=2") == (["skipped", "ran"], ["second"])
    # A change to `first` reruns both (its outputs change).
    assert run_all(tmp_path, "first.value=5", "second.value=2") == (["ran", "ran"], ["first", "second"])
    assert run_all(tmp_path, "first.value=5", "second.value=2")[0] == ["skipped", "skipped"]
    # --force reruns everything.
    assert run_all(tmp_path, "first.value=5", "second.value=2", force=True)[0] == ["ran", "ran"]


def test_tampered_output_is_not_trusted(tmp_path):
    run_all(tmp_path)
    (tmp_path / "interim" / "seqA" / "images" / "a.txt").write_text("edited")
    statuses, _ = run_all(tmp_path)
    assert statuses[0] == "ran"


def test_failed_stage_leaves_previous_outputs_and_no_staging(tmp_path):
    run_all(tmp_path)
    before = (tmp_path / "interim" / "seqA" / "gt_segments.parquet").read_bytes()
    with pytest.raises(RuntimeError, match="boom"):
        run_all(tmp_path, "second.value=-1")
    assert (tmp_path / "interim" / "seqA" / "gt_segments.parquet").read_bytes() == before
    leftovers = [p.name for p in (tmp_path / "interim" / "seqA").iterdir() if p.name.startswith(".")]
    assert leftovers == []
    # And the failed config is not recorded as done: rerunning it tries again.
    with pytest.raises(RuntimeError):
        run_all(tmp_path, "second.value=-1")


def test_missing_input_names_the_stage_to_run(tmp_path):
    r = runner(tmp_path)
    with pytest.raises(PipelineError, match=r"needs 'windows' .* run `pag first --seq seqA` first"):
        r.run(["second"])


def test_missing_raw_sequence_says_what_to_put_where(tmp_path):
    r = Runner("bup20_row3", data_root=tmp_path, show_progress=False,
               stages=[make("ing", ["raw"], ["frames"], first)])
    with pytest.raises(PipelineError, match=r"bup20_row3.*not found.*rgb/, depth/, odometry.csv"):
        r.run()


def test_atomic_write_never_leaves_partial_file(tmp_path, monkeypatch):
    path = tmp_path / "t.parquet"
    io.write_table(fake_stages.frames_df(2, 1), path, "windows")
    good = path.read_bytes()

    def exploding_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(io.os, "replace", exploding_replace)
    with pytest.raises(OSError):
        io.write_table(fake_stages.frames_df(5, 1), path, "windows")
    assert path.read_bytes() == good


def test_schema_violation_lists_columns(tmp_path):
    bad = fake_stages.frames_df(2, 1).drop(columns=["split"])
    with pytest.raises(ValueError, match=r"columns \['split'\] missing; columns present: \['window_id'"):
        io.write_table(bad, tmp_path / "x.parquet", "windows")
