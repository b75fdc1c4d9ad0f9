"""The campaign dataset: every row's tables in one Hive-partitioned Parquet dataset, a per-row summary and a report.

    data/processed/_campaign/
        fruits/seq=<SEQ>/part-0.parquet          (also counts/, window_metrics/, evaluation/)
        rows.parquet                             one row per sequence (schemas/campaign_rows.py)
        report.html                              the campaign report (pipeline/campaign_report.py)

Each partition file holds the row's table (same columns as data/processed/<SEQ>/<table>.parquet) with the
row's recording `date` as a first column; the sequence name is the partition column `seq` (from the folder
name, as Hive partitioning defines it). Every column's doc and unit travel in the file: as Arrow field
metadata ('doc', 'unit'), which pyarrow, pandas and Polars readers see, and as one JSON footer entry
'pag.columns' ({column: {doc, unit}}) that any Parquet reader can list (DuckDB: parquet_kv_metadata()).
The folder is built beside the old one and swapped into place, so readers see the previous campaign or
this one, never half of it.
"""
from __future__ import annotations

import datetime as dt
import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from pipeline import io
from pipeline.catalog import dataset
from pipeline.classes import DEFAULT_CLASSES

PARTITIONED: tuple[str, ...] = ("fruits", "counts", "window_metrics", "evaluation")
"""Row tables gathered into the campaign dataset, one Hive-partitioned folder each."""
OPTIONAL: frozenset[str] = frozenset({"evaluation"})
"""Tables a finished row may lack (evaluate disabled); the row then has no partition in that folder."""
PARTITION_COLUMN = "seq"
DATE_DOC = ("recording date of the row: a date in the sequence name (YYYY-MM-DD or YYYYMMDD) if it holds one, "
            "else the first frame's stamp_ns as a UTC date (null for stamps before 2000-01-01: a relative clock)")
_DATE_IN_NAME = re.compile(r"(?<!\d)(\d{4})-?(\d{2})-?(\d{2})(?!\d)")
_EARLIEST_STAMP_NS = 946_684_800 * 10**9  # 2000-01-01T00:00:00Z


def campaign_dir(data_root: Path) -> Path:
    """The campaign dataset's folder: data/processed/_campaign."""
    return Path(data_root) / "processed" / "_campaign"


def recording_date(seq: str, first_stamp_ns: int | None) -> tuple[dt.date | None, str]:
    """(date, source): a valid date written in the sequence name ('name'; e.g. bup20_2020-09-24_row3 for the
    BUP20 release's 2020-09-24/row3), else the first frame's stamp as a UTC date ('first_stamp'), else (None, '')."""
    for m in _DATE_IN_NAME.finditer(seq):
        try:
            return dt.date(int(m[1]), int(m[2]), int(m[3])), "name"
        except ValueError:
            continue
    if first_stamp_ns is not None and first_stamp_ns >= _EARLIEST_STAMP_NS:
        return dt.datetime.fromtimestamp(first_stamp_ns / 1e9, tz=dt.timezone.utc).date(), "first_stamp"
    return None, ""


def row_length_m(frames: pd.DataFrame) -> float:
    """Horizontal length of the camera's odometry path over the frames, in time order [m]."""
    xy = frames.sort_values("frame_id")[["tx", "ty"]].to_numpy(np.float64)
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) if len(xy) > 1 else 0.0


def _meta(field: pa.Field) -> dict[str, str]:
    return {k.decode(): v.decode() for k, v in (field.metadata or {}).items()}


def dataset_schema(table: str) -> pa.Schema:
    """The partition files' schema: `date`, then the row table's columns, each with its doc and unit."""
    base = schemas.get(table)
    fields = [schemas.col("date", pa.date32(), DATE_DOC, nullable=True), *base]
    columns = {f.name: {"doc": _meta(f).get("doc", ""), "unit": _meta(f).get("unit", "")} for f in fields}
    columns[PARTITION_COLUMN] = {"doc": "sequence name (the Hive partition folder seq=<SEQ>)", "unit": ""}
    doc = base.metadata.get(b"doc", b"").decode()
    return pa.schema(fields, metadata={
        "table": table, "doc": doc, "pag.table": table, "pag.doc": doc,
        "pag.partitioning": f"hive: {table}/{PARTITION_COLUMN}=<SEQ>/part-0.parquet",
        "pag.columns": json.dumps(columns)})


def partition_table(df: pd.DataFrame, table: str, date: dt.date | None) -> pa.Table:
    """A row's table as a partition file's content (validated against its schema, `date` prepended)."""
    t = schemas.validate(df, table)
    schema = dataset_schema(table)
    dates = pa.array([date] * t.num_rows, type=pa.date32())
    return pa.Table.from_arrays([dates, *t.columns], schema=schema)


def parquet_bytes(table: pa.Table) -> bytes:
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()


def _nan_none(v: Any) -> Any:
    return None if v is None or (isinstance(v, float) and not np.isfinite(v)) else v


def row_summary(seq: str, tables: dict[str, pd.DataFrame], frames: pd.DataFrame, date: dt.date | None,
                date_source: str, report_path: str) -> dict[str, Any]:
    """One rows.parquet row of a finished sequence."""
    counts, fruits, metrics = tables["counts"], tables["fruits"], tables["window_metrics"]
    ev = tables.get("evaluation")
    by_class = counts.set_index("class_name")["count"]
    total = int(counts["count"].sum())
    length = row_length_m(frames)
    counted = fruits[fruits.counted.astype(bool)]
    ok = metrics[metrics.status == "ok"]
    row_ev = ev[ev.scope == "row"].set_index("metric")["value"] if ev is not None and len(ev) else pd.Series(dtype=float)
    return {"seq": seq, "date": date, "date_source": date_source, "status": "ok", "error": "",
            "n_frames": len(frames), "row_length_m": length, "windows": len(metrics),
            "windows_failed": int((metrics.status != "ok").sum()), "fruits": total,
            **{f"count_{c.name}": int(by_class.get(c.name, 0)) for c in DEFAULT_CLASSES if c.is_thing},
            "fruits_per_m": total / length if length > 0 else None,
            "mean_diameter_m": _nan_none(float(counted.diameter_m.mean())) if len(counted) else None,
            "val_psnr": _nan_none(float(ok.val_psnr.mean())) if len(ok) else None,
            "pq": _nan_none(float(row_ev["pq"])) if "pq" in row_ev else None,
            "count_gt": int(row_ev["count_gt"]) if "count_gt" in row_ev and np.isfinite(row_ev["count_gt"]) else None,
            "report_path": report_path}


def failed_summary(seq: str, error: str) -> dict[str, Any]:
    return {"seq": seq, "date": None, "date_source": "", "status": "failed", "error": error, "report_path": ""}


def rows_frame(rows: list[dict[str, Any]]) -> pd.DataFrame:
    """rows.parquet's content: every schema column, nulls where a row has no value."""
    schema = schemas.get("campaign_rows")
    df = pd.DataFrame(rows, columns=schema.names)
    for f in schema:
        if pa.types.is_integer(f.type) and f.nullable:
            df[f.name] = df[f.name].astype("Int64")
        elif pa.types.is_floating(f.type):
            df[f.name] = df[f.name].astype("float64")
    return df


def load_row(data_root: Path, seq: str) -> tuple[dict[str, pd.DataFrame], pd.DataFrame]:
    """A finished row's tables (schema-checked) and its frames table."""
    tables = {}
    for name in PARTITIONED:
        path = dataset(name).path(data_root, seq)
        if name in OPTIONAL and not path.is_file():
            continue
        tables[name] = io.read_table(path, dataset(name).schema)
    return tables, io.read_table(dataset("frames").path(data_root, seq), "frames")


def write(data_root: Path, outcomes: list, season: str = "") -> Path:
    """Gather the finished rows of `outcomes` (pipeline.campaign.RowOutcome) into data/processed/_campaign/
    (replacing the previous campaign's folder atomically); returns that folder. `season`: the report's season
    section (HTML), if the rows were tracked."""
    from pipeline import campaign_report

    final = campaign_dir(data_root)
    staging = io.staging_dir(final)
    try:
        rows, gathered = [], {name: [] for name in PARTITIONED}
        for o in outcomes:
            if o.status != "ok":
                rows.append(failed_summary(o.seq, o.error))
                continue
            try:
                tables, frames = load_row(data_root, o.seq)
            except (FileNotFoundError, ValueError) as err:
                rows.append(failed_summary(o.seq, f"{type(err).__name__}: {err}"))
                continue
            date, source = recording_date(o.seq, int(frames.stamp_ns.min()) if len(frames) else None)
            report = dataset("report").path(Path("."), o.seq) / "report.html"
            has_report = (data_root / report).is_file()
            rows.append(row_summary(o.seq, tables, frames, date, source, report.as_posix() if has_report else ""))
            for name, df in tables.items():
                part = staging / name / f"{PARTITION_COLUMN}={o.seq}" / "part-0.parquet"
                io.atomic_write_bytes(part, parquet_bytes(partition_table(df, name, date)))
                gathered[name].append(df.assign(seq=o.seq, date=date))
        rows_df = rows_frame(rows)
        t = schemas.validate(rows_df, "campaign_rows")
        rows_schema = schemas.get("campaign_rows")
        columns = {f.name: {"doc": _meta(f).get("doc", ""), "unit": _meta(f).get("unit", "")} for f in rows_schema}
        t = t.replace_schema_metadata({**(rows_schema.metadata or {}), b"pag.table": b"campaign_rows",
                                       b"pag.columns": json.dumps(columns).encode()})
        io.atomic_write_bytes(staging / "rows.parquet", parquet_bytes(t))
        combined = {name: pd.concat(dfs, ignore_index=True) if dfs else None for name, dfs in gathered.items()}
        io.atomic_write_bytes(staging / "report.html", campaign_report.render(rows_df, combined, season).encode())
        io.swap_dir(staging, final)
    except Exception:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return final
