"""One pyarrow schema per table; every column carries a doc string and a unit in its metadata.

`validate(df, name)` checks a DataFrame against the named schema at a stage boundary and returns a
pyarrow Table cast to it; errors name the table and list what exists.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass

import pandas as pd
import pyarrow as pa

# Table name -> module under schemas/ that defines SCHEMA.
TABLES: tuple[str, ...] = (
    "frames",
    "detections",
    "input_checks",
    "windows",
    "gt_segments",
    "colmap_poses",
    "window_poses",
    "window_metrics",
    "renders",
    "panoptic_frames",
    "fruit_slots",
    "fruits",
    "counts",
    "structure",
    "evaluation",
    "campaign_rows",
    "fruit_tracks",
    "fruit_track_summary",
    "season_dates",
    "bench_encoding",
)


class SchemaError(ValueError):
    """A table does not match its declared schema."""


def col(name: str, type_: pa.DataType, doc: str, unit: str = "", nullable: bool = False) -> pa.Field:
    """A column with its documentation and unit ('' for unitless) stored as field metadata."""
    if not doc:
        raise ValueError(f"column {name!r} needs a doc string")
    return pa.field(name, type_, nullable=nullable, metadata={"doc": doc, "unit": unit})


def table_schema(name: str, doc: str, *fields: pa.Field) -> pa.Schema:
    return pa.schema(list(fields), metadata={"table": name, "doc": doc})


def get(name: str) -> pa.Schema:
    if name not in TABLES:
        raise KeyError(f"no schema for table {name!r}; tables: {list(TABLES)}")
    return importlib.import_module(f"schemas.{name}").SCHEMA


def describe(name: str) -> str:
    """Markdown list of a table's columns, docs and units (used by data/README.md and `pag schema`)."""
    schema = get(name)
    lines = [f"### {name}", "", schema.metadata.get(b"doc", b"").decode(), ""]
    for f in schema:
        meta = {k.decode(): v.decode() for k, v in (f.metadata or {}).items()}
        unit = f" [{meta['unit']}]" if meta.get("unit") else ""
        null = ", nullable" if f.nullable else ""
        lines.append(f"- `{f.name}` ({f.type}{null}){unit}: {meta.get('doc', '')}")
    return "\n".join(lines)


def validate(df: pd.DataFrame, name: str) -> pa.Table:
    """Check `df` against table `name` and return it as a pyarrow Table with the exact schema."""
    schema = get(name)
    if not isinstance(df, pd.DataFrame):
        raise SchemaError(f"table {name!r}: expected a pandas DataFrame, got {type(df).__name__}")
    missing = [f.name for f in schema if f.name not in df.columns]
    if missing:
        raise SchemaError(
            f"table {name!r}: columns {missing} missing; columns present: {list(df.columns)}"
        )
    extra = [c for c in df.columns if c not in schema.names]
    if extra:
        raise SchemaError(
            f"table {name!r}: columns {extra} are not in the schema (schemas/{name}.py); "
            f"declared columns: {schema.names}"
        )
    arrays = []
    for f in schema:
        series = df[f.name]
        if not f.nullable and series.isna().any():
            bad = series.index[series.isna()].tolist()[:5]
            raise SchemaError(f"table {name!r}: column {f.name!r} has nulls at rows {bad} but is not nullable")
        try:
            arrays.append(pa.array(series.tolist() if pa.types.is_list(f.type) else series,
                                   type=f.type, from_pandas=True))
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as err:
            raise SchemaError(
                f"table {name!r}: column {f.name!r} (dtype {series.dtype}) cannot be stored as {f.type}: {err}"
            ) from err
    return pa.Table.from_arrays(arrays, schema=schema)


def empty(name: str) -> pd.DataFrame:
    """An empty DataFrame with the table's columns and dtypes."""
    return get(name).empty_table().to_pandas()


@dataclass(frozen=True)
class ColumnDoc:
    name: str
    type: str
    unit: str
    doc: str
