"""Campaign settings per row, the recording-date rule and argument checks (no pipeline run)."""
import datetime as dt

import pytest
import yaml

from pipeline.campaign import as_overrides, check_seqs, row_overrides
from pipeline.campaign_dataset import recording_date
from pipeline.config import parse_set
from pipeline.runner import PipelineError, Runner


def test_as_overrides_round_trips_through_set_parsing():
    mapping = {"synth": {"seed": 2, "width": 64}, "nerf_fit": {"model": {"steps": 10}, "pose_source": "colmap"},
               "windows": {"split": [1, 2]}}
    assert parse_set(as_overrides(mapping)) == mapping


def test_row_settings_file_then_row_section_then_command_line(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump({"windows": {"half_width": 3}, "synth": {"n_frames": 12},
                                   "rows": {"synth_a": {"windows": {"half_width": 5}}, "field_row": {}}}))
    per_row = row_overrides(["synth_a", "synth_b", "field_row"], cfg, ["synth.seed=7"], tmp_path)
    resolved = {seq: Runner(seq, tmp_path, overrides=items).config for seq, items in per_row.items()}
    assert resolved["synth_a"]["windows"].half_width == 5 and resolved["synth_b"]["windows"].half_width == 3
    assert resolved["synth_a"]["synth"].seed == 7 and resolved["synth_b"]["synth"].n_frames == 12
    assert per_row["synth_a"][-1] == "synth.seed=7"
    # settings of the synth section given for all rows do not turn a recorded row into a synthetic one
    assert not any(o.startswith("synth.") for o in per_row["field_row"])
    assert not Runner("field_row", tmp_path, overrides=per_row["field_row"]).synthetic


def test_bad_sequence_lists_are_refused():
    for seqs, msg in (([], "at least one"), (["a", "a"], "more than once"), (["_campaign"], "reserved")):
        with pytest.raises(PipelineError, match=msg):
            check_seqs(seqs)


@pytest.mark.parametrize("seq, stamp, expected", [
    ("bup20_2020-09-24_row3", None, (dt.date(2020, 9, 24), "name")),
    ("20200924_row5", 1_600_000_000 * 10**9, (dt.date(2020, 9, 24), "name")),
    ("row_2020-13-45", 1_600_000_000 * 10**9, (dt.date(2020, 9, 13), "first_stamp")),  # not a date: the stamp
    ("synth_row", 1_600_000_000 * 10**9, (dt.date(2020, 9, 13), "first_stamp")),
    ("synth_row", 12 * 10**9, (None, "")),  # a relative clock
])
def test_recording_date_rule(seq, stamp, expected):
    assert recording_date(seq, stamp) == expected
