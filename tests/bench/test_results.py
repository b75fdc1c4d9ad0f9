"""`pag bench results`: the README's results block is generated from tables on disk, with their commits."""
import json

import pandas as pd
import pytest

from bench import results
from bench._common import write_parquet


def _row(tmp_path, commit="abc123"):
    proc = tmp_path / "processed" / "synth_x"
    proc.mkdir(parents=True)
    pd.DataFrame({"scope": ["row", "windows_mean", "row"], "metric": ["pq", "psnr", "count_pred"],
                  "value": [0.91, 27.5, 12.0]}).to_parquet(proc / "evaluation.parquet")
    man = tmp_path / "interim" / "synth_x" / "_manifest"
    man.mkdir(parents=True)
    (man / "evaluate.json").write_text(json.dumps({"code_version": commit}))


def test_block_shows_measured_values_and_their_commits(tmp_path):
    _row(tmp_path)
    bench = tmp_path / "bench"
    write_parquet(pd.DataFrame({"workers": [1, 2], "windows": [4, 4], "steps": [10, 10], "wall_s": [9.0, 5.0],
                                "speedup_vs_1": [1.0, 1.8]}), bench / "dask.parquet")
    text = results.build(tmp_path, bench, "synth_x")
    assert "commit `abc123`" in text
    assert "| PQ, fused row (NeRF) | 0.910 |" in text
    assert "| val PSNR, mean over windows (dB) | 27.50 |" in text
    assert "| fruits counted | 12 |" in text
    from pipeline.provenance import code_version
    assert f"`pag bench dask`), commit `{code_version()}`" in text
    assert "| 2 | 4 | 10 | 5 | 1.8 |" in text
    assert "`pag bench encoding`" in text.split("Not measured")[1]


def test_replace_block_keeps_the_rest_of_the_readme(tmp_path):
    readme = f"# T\nintro\n{results.START}\nold numbers\n{results.END}\nafter\n"
    out = results.replace_block(readme, "new table")
    assert out == f"# T\nintro\n{results.START}\nnew table\n{results.END}\nafter\n"
    with pytest.raises(ValueError, match="no results block"):
        results.replace_block("# no markers\n", "x")


def test_missing_evaluation_is_named_not_invented(tmp_path):
    text = results.build(tmp_path, tmp_path / "bench", "synth_none")
    assert "No evaluation of `synth_none` on disk" in text


def test_a_partly_run_family_says_which_rows_its_mean_covers(tmp_path):
    from bench._row_family import FAMILY
    first, second = FAMILY[0].name, FAMILY[1].name
    table = pd.DataFrame({"row": [first, second, "mean", "worst"], "count_error_rel": [0.0, -0.04, -0.02, -0.04]})
    write_parquet(table, tmp_path / "rows.parquet")
    text = results.family_section(tmp_path / "rows.parquet")
    assert f"2 of the family's {len(FAMILY)} rows finished" in text
    assert FAMILY[2].name in text.split("not yet run:")[1].split(")")[0]
    assert f"| {second} | -0.04 |" in text
    whole = pd.DataFrame({"row": [r.name for r in FAMILY] + ["mean"], "count_error_rel": 0.0})
    write_parquet(whole, tmp_path / "rows.parquet")
    assert "not yet run" not in results.family_section(tmp_path / "rows.parquet")
    # the held-out rows have their own head and their own list of rows
    from bench._row_family import HOLDOUT
    write_parquet(pd.DataFrame({"row": [HOLDOUT[0].name, "mean"], "count_error_rel": 0.0}),
                  tmp_path / "rows_holdout.parquet")
    text = results.family_section(tmp_path / "rows_holdout.parquet", "rows_holdout")
    assert text.startswith("Held-out rows (`pag bench rows --holdout`)")
    assert f"1 of the held-out {len(HOLDOUT)} rows finished" in text and HOLDOUT[1].name in text


def test_fit_seed_tables_are_shown_beside_the_seed_0_rows(tmp_path):
    write_parquet(pd.DataFrame({"row": ["dense", "densest", "mean"], "row_id_consistency": [0.87, 0.72, 0.8],
                                "pq": [0.9, 0.88, 0.89]}), tmp_path / "rows.parquet")
    write_parquet(pd.DataFrame({"row": ["densest", "mean"], "fit_seed": [1, None],
                                "row_id_consistency": [0.79, 0.79], "pq": [0.885, 0.885]}),
                  tmp_path / "rows_seed1.parquet")
    text = results.seeds_section(tmp_path, [tmp_path / "rows_seed1.parquet"])
    assert text.startswith("Row family on other fit seeds") and "seed 1:" in text
    assert "| densest | 0 | 0.72 | 0.88 |" in text and "| densest | 1 | 0.79 | 0.885 |" in text
    assert "| dense |" not in text and "| mean |" not in text  # only rows fitted on both seeds
    block = results.build(tmp_path, tmp_path, "synth_none")
    assert "Row family on other fit seeds" in block
    assert "Row family on other fit seeds" not in results.build(tmp_path / "x", tmp_path / "x", "synth_none")


def test_count_rules_section_lists_each_row_and_each_verdict(tmp_path):
    runs = pd.DataFrame({"seq": ["synth_a", "synth_a", ""], "variant": ["all rules", "far_row off", "far_row off"],
                         "rule": ["all rules", "far_row", "far_row"], "count_pred": [10.0, 12.0, None],
                         "count_gt": [10.0, 10.0, None], "count_error_rel": [0.0, 0.2, None],
                         "recall": [1.0, 1.0, None], "precision": [1.0, 0.833, None], "f1": [1.0, 0.909, None],
                         "helps": [None, None, "synth_a"], "hurts": [None, None, ""], "verdict": [None, None, "keep"]})
    write_parquet(runs, tmp_path / "count_rules.parquet")
    text = results.count_rules_section(tmp_path / "count_rules.parquet")
    assert "| synth_a | far_row off | 12 | 10 | 0.2 | 1 | 0.833 | 0.909 |" in text
    assert "| far_row | synth_a |  | keep |" in text
    _row(tmp_path)
    assert "`pag bench count_rules`" in results.build(tmp_path, tmp_path, "synth_x")


def test_scale_section_sums_each_variant_and_shows_the_exponents(tmp_path):
    base = {"sweep": "frames", "seq": "synth_scale_40f_320x180", "n_frames": 40, "width": 320, "height": 180,
            "n_windows": 1, "psnr_db": 29.1, "pq": 0.92, "count_error_rel": -0.05}
    table = pd.DataFrame([{**base, "stage": "synth", "seconds": 30.0, "peak_rss_mb": 500.0},
                          {**base, "stage": "nerf_fit", "seconds": 210.0, "peak_rss_mb": 2000.0}])
    write_parquet(table, tmp_path / "scale.parquet")
    write_parquet(pd.DataFrame({"sweep": ["frames"], "stage": ["nerf_fit"], "time_exponent": [0.75],
                                "memory_exponent": [0.5], "seconds_max": [210.0], "peak_rss_mb_max": [2000.0]}),
                  tmp_path / "scale_exponents.parquet")
    text = results.scale_section(tmp_path / "scale.parquet")
    assert "| frames | 40 | 320 | 180 | 1 | 4 | 2e+03 | 29.1 | 0.92 | -0.05 |" in text  # 240 s = 4 min
    assert "| frames | nerf_fit | 0.75 | 0.5 | 210 | 2e+03 |" in text


def test_real_row_table_sums_the_stages_with_and_without_synthesis_and_the_section_shows_them(tmp_path):
    from bench import real_row

    stages = pd.DataFrame({"stage": ["synth", "ingest", "nerf_fit"], "seconds": [540.0, 60.0, 1800.0],
                           "peak_rss_mb": [1500.0, 1400.0, 6000.0], "code_version": ["aaa", "aaa", "bbb"]})
    df = real_row.table(stages, {"n_frames": 450, "width": 1280, "height": 720, "n_windows": 13},
                        {"count_gt": 70.0, "count_pred": 69.0, "pq": 0.9})
    tot = df.set_index("stage")
    assert tot.loc["total", "seconds"] == 2400 and tot.loc["total", "peak_rss_mb"] == 6000
    assert tot.loc["after_synth", "seconds"] == 1860 and tot.loc["after_synth", "minutes"] == 31
    assert (df.n_windows == 13).all() and (df.pq == 0.9).all()
    write_parquet(df, tmp_path / "real_row.parquet")
    text = results.real_row_section(tmp_path / "real_row.parquet")
    assert "1280x720, 450 frames, 13 windows" in text
    assert "| nerf_fit | 30 | 6e+03 | bbb |" in text and "| after_synth | 31 | 6e+03 |  |" in text
    assert "| 70 | 69 | 0.9 |" in text


def test_a_table_not_on_disk_keeps_the_readme_section_with_its_commit(tmp_path):
    # a README whose block was generated where the encoding and render benches ran, and another default row
    _row(tmp_path, commit="new111")
    bench = tmp_path / "bench"
    write_parquet(pd.DataFrame({"workers": [1], "windows": [4], "steps": [10], "wall_s": [9.0],
                                "speedup_vs_1": [1.0]}), bench / "dask.parquet")
    old = "\n\n".join([
        "Encoding (`pag bench encoding`), fused permutohedral kernel, commit `old000`; ratios:\n\n| a |\n|---|\n| 1 |",
        "`synth_x` (`pag all --seq synth_x`), commit `old000`:\n\n| metric | value |\n|---|---|\n| PQ | 0.5 |",
        "Dask workers (`pag bench dask`), commit `old000`:\n\n| workers |\n|---|\n| 7 |",
        "Not measured in this checkout: `pag bench render`."])
    text = results.build(tmp_path, bench, "synth_x", previous=old)
    assert "Encoding (`pag bench encoding`), fused permutohedral kernel, commit `old000`" in text
    assert "| a |\n|---|\n| 1 |" in text.split("Encoding")[1]
    # tables on disk replace their old sections; what is in neither place is named
    assert "commit `new111`" in text and "| PQ | 0.5 |" not in text and "| 7 |" not in text
    assert text.rstrip().endswith("Not measured in this checkout: `pag bench rows`, `pag bench rows --holdout`, "
                                  "`pag bench rows --unseen`, "
                                  "`pag bench count_rules`, `pag bench fusion_terms`, "
                                  "`pag bench scale`, `pag bench real_row`, `pag bench real_rgbd`, `pag bench render`.")
    assert results.current_block(f"x\n{results.START}\n{old}\n{results.END}\n").strip() == old
