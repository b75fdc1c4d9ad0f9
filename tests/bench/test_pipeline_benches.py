"""pag bench rows / scale / count_rules: the family, the shared variant runner (one real tiny row through
every stage), checkpointing, the summary rows, the growth exponents and the counting-rule check."""
import json

import numpy as np
import pandas as pd
import pytest

from bench import _pipeline, count_rules, fusion_terms, rows, scale
from bench._row_family import FAMILY, HOLDOUT, QUICK, UNSEEN, family_row


def test_family_spans_the_required_knobs():
    assert len(FAMILY) >= 8 and len({r.name for r in FAMILY}) == len(FAMILY)
    assert len({r.seed for r in FAMILY}) == len(FAMILY)
    dens = [r.fruits_per_m for r in FAMILY]
    assert min(dens) == 8 and max(dens) == 40
    assert min(r.det_miss_rate for r in FAMILY) <= 0.05 and max(r.det_miss_rate for r in FAMILY) >= 0.35
    assert min(r.det_false_pos_rate for r in FAMILY) <= 0.1 and max(r.det_false_pos_rate for r in FAMILY) >= 0.6
    assert max(r.odom_drift_m_per_m for r in FAMILY) == 0.06 and max(r.odom_yaw_drift_deg_per_m for r in FAMILY) == 4
    assert {min(r.n_frames for r in FAMILY), max(r.n_frames for r in FAMILY)} == {120, 240}
    assert len(QUICK) == 4 and all(family_row(n) for n in QUICK)
    with pytest.raises(ValueError, match="no row 'nope' in the family; rows:"):
        family_row("nope")


def test_holdout_rows_share_no_seed_or_knob_set_with_the_family():
    assert HOLDOUT and len({r.name for r in (*FAMILY, *HOLDOUT)}) == len(FAMILY) + len(HOLDOUT)
    assert not {r.seed for r in HOLDOUT} & {r.seed for r in FAMILY}
    knobs = [{k: v for k, v in r.knobs().items() if k != "seed"} for r in FAMILY]
    for r in HOLDOUT:
        assert {k: v for k, v in r.knobs().items() if k != "seed"} not in knobs
        assert 8 <= r.fruits_per_m <= 40 and r.n_frames % 40 == 0 and family_row(r.name) is r
    for argv in (["--quick", "--holdout"], ["--rows", HOLDOUT[0].name], ["--holdout", "--rows", FAMILY[0].name],
                 ["--fit-seed", "-1"]):
        with pytest.raises(SystemExit):  # before anything runs
            rows.main(argv)


def test_unseen_rows_share_no_seed_or_knob_value_with_any_earlier_row():
    earlier = (*FAMILY, *HOLDOUT)
    assert len(UNSEEN) >= 4 and not {r.seed for r in UNSEEN} & {r.seed for r in earlier}
    every = (*earlier, *UNSEEN)
    assert len({r.seed for r in every}) == len(every)   # a new unseen row reuses no unseen row's seed either
    knobs = ("fruits_per_m", "det_miss_rate", "det_false_pos_rate", "det_merge_rate", "odom_drift_m_per_m",
             "odom_yaw_drift_deg_per_m", "n_frames")
    for knob in knobs:
        assert not {getattr(r, knob) for r in UNSEEN} & {getattr(r, knob) for r in earlier}, knob
    assert all(family_row(r.name) is r and r.n_labelled >= 3 for r in UNSEEN)
    newest = [r for r in UNSEEN if r.name.split("_")[0] == UNSEEN[-1].name.split("_")[0]]
    others = [r for r in every if r not in newest]
    for knob in knobs:   # the rows defined last repeat no value of any row
        assert not {getattr(r, knob) for r in newest} & {getattr(r, knob) for r in others}, knob
    for argv in (["--unseen", "--holdout"], ["--rows", UNSEEN[0].name], ["--unseen", "--rows", HOLDOUT[0].name]):
        with pytest.raises(SystemExit):  # before anything runs
            rows.main(argv)


def test_a_fit_seed_row_is_its_own_sequence_with_the_seed_set():
    assert rows.row_seq("dense") == "synth_rows_dense" and rows.row_seq("dense", fit_seed=2) == "synth_rows_dense_seed2"
    assert rows.row_seq("dense", quick=True) == "synth_rowsq_dense"
    assert "nerf_fit.seed=2" in rows.row_settings("dense", False, 2)
    assert not any(s.startswith("nerf_fit.seed") for s in rows.row_settings("dense", False))


def test_growth_exponent():
    assert _pipeline.growth_exponent(np.array([60, 120, 240]), np.array([2.0, 4.0, 8.0])) == pytest.approx(1.0)
    assert _pipeline.growth_exponent(np.array([1, 2, 4]), np.array([1.0, 4.0, 16.0])) == pytest.approx(2.0)
    assert np.isnan(_pipeline.growth_exponent(np.array([5, 5]), np.array([1.0, 2.0])))


def test_summary_rows_take_the_worst_in_the_right_direction():
    df = pd.DataFrame([{"row": "a", "count_error_rel": -0.10, "recall": 0.9, "diameter_median_err_m": 0.002,
                        "minutes": 3.0, "peak_rss_mb": 100.0},
                       {"row": "b", "count_error_rel": 0.05, "recall": 0.8, "diameter_median_err_m": 0.004,
                        "minutes": 1.0, "peak_rss_mb": 300.0}])
    for c in _pipeline.QUALITY:
        if c not in df:
            df[c] = np.nan
    out = rows.summarise(df).set_index("row")
    assert out.loc["mean", "recall"] == pytest.approx(0.85)
    assert out.loc["worst", "count_error_rel"] == -0.10 and out.loc["worst", "recall"] == 0.8
    assert out.loc["worst", "diameter_median_err_m"] == 0.004 and out.loc["worst", "minutes"] == 3.0
    assert np.isnan(out.loc["worst", "pq"])


@pytest.mark.slow  # about 30 s: the quick row family through the pipeline
def test_rows_quick_runs_the_pipeline_and_is_checkpointed(tmp_path, capsys):
    data, out = tmp_path / "data", tmp_path / "bench"
    assert rows.main(["--quick", "--rows", "dense", "--data-root", str(data), "--out", str(out)]) == 0
    df = pd.read_parquet(out / "rows_quick.parquet")
    assert list(df.row) == ["dense", "mean", "worst"]
    r = df.iloc[0]
    assert r.fruits_per_m == family_row("dense").fruits_per_m and r.n_frames == 14
    assert r.count_gt > 0 and np.isfinite(r.count_error_rel) and np.isfinite(r.psnr_db) and np.isfinite(r.pq_detector)
    assert r.minutes > 0 and r.peak_rss_mb > 50
    ev = pd.read_parquet(data / "processed" / "synth_rowsq_dense" / "evaluation.parquet").set_index(["scope", "metric"])
    for kind in ("unlabelled", "shared", "split"):  # why fruits fail the ID consistency, from evaluate
        assert r[f"id_fail_{kind}"] == ev.loc[("row", f"id_fail_{kind}"), "value"]
    manifest = json.loads((data / "interim" / "synth_rowsq_dense" / "_manifest" / "nerf_fit.json").read_text())
    assert manifest["peak_rss_mb"] > 0
    assert (out / "rows_quick.png").is_file()
    capsys.readouterr()
    assert rows.main(["--quick", "--rows", "dense", "--data-root", str(data), "--out", str(out)]) == 0
    assert "dense: done before, skipped" in capsys.readouterr().err
    with pytest.raises(ValueError, match="no row 'nope'"):
        rows.main(["--quick", "--rows", "nope", "--out", str(out)])

    # the counting rules, checked on the finished row: fruit_count and evaluate rerun through the runner
    before = {p: p.stat().st_mtime_ns for p in (data / "processed" / "synth_rowsq_dense").glob("*.parquet")}
    assert count_rules.main(["--quick", "--data-root", str(data), "--out", str(out)]) == 0  # finished rows
    cr = pd.read_parquet(out / "count_rules_quick.parquet")
    runs = cr[cr.seq == "synth_rowsq_dense"].set_index("variant")
    assert list(runs.index) == ["all rules", *(f"{k} off" for k in count_rules.RULES_OFF)]
    base = runs.loc["all rules"]
    for col in ("count_pred", "count_gt", "recall", "precision"):  # the same scores as the pipeline's own run
        assert base[col] == pytest.approx(r[col], nan_ok=True)
    excluding = [f"{k} off" for k in count_rules.RULES_OFF if k != "end_tracks"]
    assert (runs.loc[excluding, "count_pred"] >= base.count_pred).all()  # a rule leaving fruits out, off: never fewer
    assert runs.loc["end_tracks off", "count_pred"] <= base.count_pred    # the rule adding fruits, off: never more
    verdict = cr[cr.seq == ""].set_index("rule")
    for rule in count_rules.RULES_OFF:
        delta = runs.loc[f"{rule} off", "f1"] - base.f1
        tol = count_rules.TOLERANCE   # F1s computed from other counts can differ in the last bit
        expect = "keep" if delta < -tol else "drop" if delta > tol else "no effect"
        assert verdict.loc[rule, "verdict"] == expect or not np.isfinite(delta), delta
    assert before == {p: p.stat().st_mtime_ns for p in before}  # the row's own tables untouched
    with pytest.raises(ValueError, match="no rows to check"):
        count_rules.main(["--data-root", str(data), "--out", str(out)])  # the full family has not run here
    with pytest.raises(FileNotFoundError, match="run `pag all --seq synth_none`"):
        count_rules.main(["--seqs", "synth_none", "--data-root", str(data), "--out", str(out)])

    # the fusion's cost terms, each switched off on the finished row: fusion, counting and evaluate rerun
    assert fusion_terms.main(["--quick", "--data-root", str(data), "--out", str(out)]) == 0
    ft = pd.read_parquet(out / "fusion_terms_quick.parquet")
    runs = ft[ft.seq == "synth_rowsq_dense"].set_index("variant")
    assert list(runs.index) == ["all terms", *(f"{t} off" for t in fusion_terms.TERMS)]
    assert runs.loc["all terms", "row_id"] == pytest.approx(r["row_id_consistency"], nan_ok=True)
    assert set(ft[ft.seq == ""].verdict) <= {"keep", "mixed", "drop", "no effect"}
    assert before == {p: p.stat().st_mtime_ns for p in before}


def test_count_rules_rerun_each_stage_with_the_settings_the_row_ran_with(tmp_path):
    resolved = tmp_path / "processed" / "synth_x" / "config.resolved.yaml"
    resolved.parent.mkdir(parents=True)
    resolved.write_text("fruit_count:\n  max_depth_m: 2.5\n  a_setting_since_removed: 1\nwindows:\n  half_width: 3\n")
    assert count_rules.row_config(tmp_path, "synth_x") == {"fruit_count": {"max_depth_m": 2.5}, "evaluate": {}}
    assert count_rules.row_config(tmp_path, "synth_y") == {"fruit_count": {}, "evaluate": {}}  # no file: defaults


def test_count_rule_verdicts_weigh_every_row():
    f1 = {("a", "all rules"): 0.9, ("b", "all rules"): 0.8,
          ("a", "fragments off"): 0.85, ("b", "fragments off"): 0.85,    # helps a, hurts b: mixed
          ("a", "unconfirmed off"): 0.88, ("b", "unconfirmed off"): 0.8,  # helps a only: keep
          ("a", "far_row off"): 0.9, ("b", "far_row off"): 0.8}           # changes nothing
    df = pd.DataFrame([{"seq": s, "variant": v, "f1": x} for (s, v), x in f1.items()])
    v = count_rules.verdicts(df).set_index("rule")
    assert v.loc["fragments", "verdict"] == "mixed" and v.loc["fragments", "helps"] == "a"
    assert v.loc["fragments", "hurts"] == "b"
    assert v.loc["unconfirmed", "verdict"] == "keep" and v.loc["far_row", "verdict"] == "no effect"
    df.loc[(df.seq == "b") & (df.variant == "far_row off"), "f1"] = 0.81
    assert count_rules.verdicts(df).set_index("rule").loc["far_row", "verdict"] == "drop"


def test_scale_sweeps_tables_and_exponents(tmp_path, monkeypatch):
    """The scale harness around a stand-in variant runner whose costs grow as frames^1 and pixels^0.5."""
    calls = []

    def fake_run_variant(seq, overrides, data_root, force=False):
        knobs = dict(o.split("=", 1) for o in overrides)
        n, w, h = int(knobs["synth.n_frames"]), int(knobs["synth.width"]), int(knobs["synth.height"])
        calls.append(seq)
        stages = pd.DataFrame({"stage": ["synth", "nerf_fit"], "seconds": [0.1 * n, 0.01 * n * (w * h) ** 0.5],
                               "peak_rss_mb": [100.0, 100.0]})
        return _pipeline.VariantRun(seq, 1.0, stages, {c: 0.5 for c in _pipeline.QUALITY})

    monkeypatch.setattr(scale, "run_variant", fake_run_variant)
    df, ex = scale.run([10, 20, 40], [(48, 32), (96, 64)], quick=True, data_root=tmp_path, out_dir=tmp_path)
    assert len(set(calls)) == 4  # the shared point (10 frames, 48x32) is one sequence
    e = ex.set_index(["sweep", "stage"])
    assert e.loc[("frames", "synth"), "time_exponent"] == pytest.approx(1.0)
    assert e.loc[("pixels", "nerf_fit"), "time_exponent"] == pytest.approx(0.5)
    assert e.loc[("pixels", "synth"), "time_exponent"] == pytest.approx(0.0, abs=1e-9)
    assert e.loc[("frames", "nerf_fit"), "memory_exponent"] == pytest.approx(0.0, abs=1e-9)
    assert set(df.columns) >= {"sweep", "n_frames", "pixels", "stage", "seconds", "peak_rss_mb", "pq", "psnr_db"}
    for name in ("scale_quick.parquet", "scale_quick_exponents.parquet", "scale_quick.png"):
        assert (tmp_path / name).is_file()
    with pytest.raises(ValueError, match="expected WxH"):
        scale.parse_sizes("320x180,big")


def test_fusion_term_verdicts_read_row_id_then_f1_then_pq():
    rows = []
    for seq, variant, row_id, f1, pq in [("a", "all terms", 0.95, 0.9, 0.90), ("b", "all terms", 1.0, 1.0, 0.90),
                                         ("a", "render off", 0.90, 0.95, 0.95), ("b", "render off", 1.0, 1.0, 0.9),
                                         ("a", "shape off", 0.95, 0.9, 0.92), ("b", "shape off", 1.0, 0.95, 0.99)]:
        rows.append({"seq": seq, "variant": variant, "row_id": row_id, "f1": f1, "pq": pq})
    rows += [{"seq": s, "variant": f"{t} off", "row_id": r, "f1": 0.9 if s == "a" else 1.0, "pq": 0.9}
             for t in fusion_terms.TERMS if t not in ("render", "shape") for s, r in (("a", 0.95), ("b", 1.0))]
    v = fusion_terms.verdicts(pd.DataFrame(rows)).set_index("term")
    assert v.loc["render", "verdict"] == "keep" and v.loc["render", "helps"] == "a"   # row ID decides over PQ
    assert v.loc["shape", "verdict"] == "mixed"      # hurts a (PQ rises), helps b (F1 falls)
    assert v.loc["order", "verdict"] == "no effect"
