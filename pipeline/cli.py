"""`pag`: run one stage, the whole DAG, an evaluation or a benchmark.

    pag <stage> --seq SEQ [--config FILE] [--set key=value ...] [--force]
    pag all --seq SEQ [--from STAGE] [--to STAGE] [--force]
    pag campaign --seqs SEQ [SEQ ...] [--scheduler ADDRESS] [--track]   every row, windows on one Dask
                                         cluster, then data/processed/_campaign/ (docs/campaign.md); --track
                                         also links the rows as dates of one row (docs/season.md)
    pag track --seqs SEQ[@DATE] ...      one row's season: fruits tracked across dates (docs/season.md)
    pag bench <name> [args ...]          (bench/<name>.py; `pag bench list`)
    pag config --seq SEQ [--doc]         resolved config (with field docs)
    pag schema [TABLE]                   table columns, units and docs
    pag stages                           the DAG
Exit code 0 on success; otherwise a one-paragraph error on stderr and a non-zero code.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
import traceback
from pathlib import Path

from pipeline.dag import STAGE_ORDER


def _run_options(p: argparse.ArgumentParser, config_help: str = "YAML file with config sections") -> None:
    """Options of every command that runs stages (one row, all stages, a campaign)."""
    p.add_argument("--config", type=Path, default=None, help=config_help)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set synth.seed=3 (repeatable)")
    p.add_argument("--data-root", type=Path, default=Path("data"), help="data folder (default: ./data)")
    p.add_argument("--force", action="store_true", help="rerun even if inputs and config are unchanged")
    p.add_argument("--no-progress", action="store_true", help="hide progress (bars on a terminal, lines in a log)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="dask.distributed scheduler address for nerf_fit (default: a local cluster)")
    p.add_argument("--debug", action="store_true", help="show tracebacks")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seq", default="synth_row", help="sequence folder under data/raw/ (default: synth_row)")
    _run_options(p)


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(prog="pag", description=__doc__.split("\n")[0],
                                  formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in STAGE_ORDER:
        _common(sub.add_parser(name, help=f"run the {name} stage"))
    p_all = sub.add_parser("all", help="run every stage in order, skipping unchanged ones")
    _common(p_all)
    p_all.add_argument("--from", dest="from_stage", choices=STAGE_ORDER, default=None, help="first stage to run")
    p_all.add_argument("--to", dest="to_stage", choices=STAGE_ORDER, default=None, help="last stage to run")
    p_camp = sub.add_parser("campaign", help="run many rows, their windows on one Dask cluster, and gather "
                            "their tables into data/processed/_campaign/")
    p_camp.add_argument("--seqs", nargs="+", required=True, metavar="SEQ", help="sequence folders under data/raw/")
    _run_options(p_camp, "YAML file with config sections, and per-row ones under rows: {SEQ: {...}}")
    p_camp.add_argument("--track", action="store_true", help="track the finished rows as dates of one row "
                        "(as `pag track`, default track settings) and add a season section to the report")
    p_track = sub.add_parser("track", help="track one row's fruits across recording dates into "
                             "data/processed/_season/ (docs/season.md)")
    p_track.add_argument("--seqs", nargs="+", required=True, metavar="SEQ[@DATE]",
                         help="finished rows of the same row on different dates; @YYYY-MM-DD gives a date")
    p_track.add_argument("--set", dest="overrides", action="append", default=[], metavar="track.KEY=VALUE",
                         help="a tracking setting, e.g. --set track.gate_m=0.04 (repeatable)")
    p_track.add_argument("--data-root", type=Path, default=Path("data"), help="data folder (default: ./data)")
    p_track.add_argument("--name", default="_season", help="dataset folder under data/processed/ (default: _season)")
    p_track.add_argument("--debug", action="store_true", help="show tracebacks")
    p_cfg = sub.add_parser("config", help="print the resolved config")
    _common(p_cfg)
    p_cfg.add_argument("--doc", action="store_true", help="with each field's documentation")
    p_schema = sub.add_parser("schema", help="print table schemas (columns, units, docs)")
    p_schema.add_argument("table", nargs="?", default=None)
    sub.add_parser("stages", help="list the stages and their inputs/outputs")
    p_bench = sub.add_parser("bench", help="run a benchmark from bench/ (`pag bench list`)")
    p_bench.add_argument("name", help="benchmark name, or 'list'")
    p_bench.add_argument("args", nargs=argparse.REMAINDER, help="arguments for the benchmark")
    return top


def _runner(args: argparse.Namespace):
    from pipeline.runner import Runner

    overrides = list(args.overrides)
    if args.scheduler:
        overrides.append(f"run.scheduler={args.scheduler}")
    return Runner(args.seq, data_root=args.data_root, config_file=args.config, overrides=overrides,
                  show_progress=False if args.no_progress else None)


def _bench(name: str, argv: list[str]) -> int:
    import bench

    names = sorted(m.name for m in pkgutil.iter_modules(bench.__path__) if not m.name.startswith("_"))
    if name == "list":
        print("\n".join(names))
        return 0
    if name not in names:
        raise ValueError(f"no benchmark {name!r}; benchmarks: {names}")
    mod = importlib.import_module(f"bench.{name}")
    return int(mod.main(argv) or 0)


def _campaign(args: argparse.Namespace) -> int:
    from pipeline.campaign import run_campaign
    from pipeline.campaign_dataset import campaign_dir

    outcomes = run_campaign(args.seqs, data_root=args.data_root, config_file=args.config,
                            overrides=list(args.overrides), scheduler=args.scheduler, force=args.force,
                            show_progress=False if args.no_progress else None, track=args.track)
    failed = [o for o in outcomes if o.status != "ok"]
    for o in failed:
        print(f"pag campaign: row {o.seq} failed: {o.error}", file=sys.stderr)
    out = campaign_dir(args.data_root)
    print(f"[pag] campaign: {len(outcomes) - len(failed)} of {len(outcomes)} rows ok; dataset {out}; "
          f"report: {(out / 'report.html').resolve()}")
    return 1 if failed else 0


def _track(args: argparse.Namespace) -> int:
    from pipeline import season

    if not args.name.startswith("_"):
        raise ValueError(f"--name {args.name!r}: season folders start with '_' (other names are sequences)")
    result, scores, out = season.track(args.seqs, args.data_root, args.overrides, args.name)
    d = result.dates
    for r in d.itertuples(index=False):
        print(f"[pag track] {r.seq} (day {r.day:.1f}): {r.fruits} fruits, {r.continued} continued, {r.set} set, "
              f"{r.harvested} harvested; registered by {r.registration_inliers} fruits")
    for k in ("association_precision", "association_recall", "idf1", "registration_error_median_m",
              "growth_error_median_mm_per_week", "event_f1", "tracking_cost_share"):
        if k in scores:
            print(f"[pag track] {k} = {scores[k]:.4g}")
    print(f"[pag track] {result.tracks.track_id.nunique()} tracks; dataset {out}; report: {(out / 'report.html').resolve()}")
    return 0


def dispatch(args: argparse.Namespace) -> int:
    if args.command == "stages":
        from pipeline import dag

        for s in dag.build():
            print(f"{s.name:16s} in: {', '.join(s.inputs + s.optional_inputs) or '-':40s} out: {', '.join(s.outputs)}")
        return 0
    if args.command == "schema":
        import schemas

        for t in [args.table] if args.table else schemas.TABLES:
            print(schemas.describe(t) + "\n")
        return 0
    if args.command == "bench":
        return _bench(args.name, args.args)
    if args.command == "campaign":
        return _campaign(args)
    if args.command == "track":
        return _track(args)
    runner = _runner(args)
    if args.command == "config":
        from pipeline import config as cfgmod

        for section, value in runner.config.items():
            if args.doc:
                print("\n".join(cfgmod.describe(section, type(value), value)))
            else:
                print(f"{section}: {cfgmod.to_dict(value)}")
        return 0
    if args.command == "all":
        # --from/--to name places in the stage order, also a stage this config leaves out (colmap_poses)
        lo = STAGE_ORDER.index(args.from_stage) if args.from_stage else 0
        hi = STAGE_ORDER.index(args.to_stage) if args.to_stage else len(STAGE_ORDER)
        runner.run([s.name for s in runner.active() if lo <= STAGE_ORDER.index(s.name) <= hi], force=args.force)
        print(f"[pag] outputs: {(runner.data_root / 'interim' / runner.seq).resolve()} and "
              f"{(runner.data_root / 'processed' / runner.seq).resolve()}")
        _print_report_path(runner)
        return 0
    runner.run([args.command], force=args.force)
    if args.command == "report":
        _print_report_path(runner)
    return 0


def _print_report_path(runner) -> None:
    """Where the row's report is, under the run's data root (`--data-root`), the one place that says it
    (`make all` prints nothing of its own)."""
    from pipeline.catalog import dataset

    report = dataset("report").path(runner.data_root, runner.seq) / "report.html"
    if report.is_file():
        print(f"[pag] report: {report.resolve()}")


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if getattr(args, "debug", False) else logging.WARNING,
                        format="[pag] %(message)s")
    try:
        return dispatch(args)
    except KeyboardInterrupt:
        print("pag: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # one paragraph for the user; --debug for the traceback
        if getattr(args, "debug", False):
            traceback.print_exc()
        kind = type(err).__name__
        print(f"pag {args.command}: error: {err}" + ("" if getattr(args, "debug", False) else
              f" ({kind}; rerun with --debug for the traceback)"), file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
