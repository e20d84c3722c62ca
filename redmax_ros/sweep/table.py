"""The results table of a sweep, written row by row as runs finish.

``TableWriter`` appends each row to a CSV file and flushes it (os.fsync too), so a sweep that crashes or is
killed keeps every finished row, and ``--resume`` can skip them. Floats are written with ``repr`` (the
shortest text that reads back as the same float64), None as an empty field. ``write_parquet`` writes the
whole table (sorted by run) once the sweep has ended, with pyarrow.
"""
from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq


def cell(v) -> str:
    """The CSV text of one value: repr for floats (exact), '' for None."""
    if v is None:
        return ""
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        return repr(v)
    return str(v)


class TableWriter:
    """A CSV results table with fixed ``columns``; ``append=True`` continues an existing file with the same
    header (ValueError if its header differs)."""

    def __init__(self, path, columns, append: bool = False):
        self.path, self.columns = Path(path), list(columns)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if append and self.path.exists() and self.path.stat().st_size > 0:
            with open(self.path, newline="") as f:
                header = next(csv.reader(f), None)
            if header != self.columns:
                raise ValueError(f"{self.path}: its columns differ from this sweep's; cannot resume")
            self.f = open(self.path, "a", newline="")
        else:
            self.f = open(self.path, "w", newline="")
            self._write(self.columns)

    def _write(self, fields):
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerow(fields)
        self.f.write(buf.getvalue())
        self.f.flush()
        os.fsync(self.f.fileno())

    def write(self, row: dict) -> None:
        """Append one row (missing columns empty) and flush it to disk."""
        self._write([cell(row.get(c)) for c in self.columns])

    def close(self):
        self.f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_table(path) -> tuple:
    """(columns, rows as dicts of text) of a CSV results table; a last line cut short by a crash is dropped."""
    with open(path, newline="") as f:
        text = f.read()
    lines = list(csv.reader(io.StringIO(text)))
    if not lines:
        return [], []
    cols = lines[0]
    body = lines[1:]
    if body and not text.endswith("\n"):
        body = body[:-1]
    return cols, [dict(zip(cols, r)) for r in body if len(r) == len(cols)]


def number(text):
    """float(text), None for '' or text that is not a number."""
    if text is None or text == "":
        return None
    try:
        return float(text)
    except ValueError:
        return None


def write_parquet(path, columns, rows) -> Path:
    """The rows (dicts; sorted by 'run') as a Parquet file; each column float64 / int64 / string as its
    values allow."""
    rows = sorted(rows, key=lambda r: r["run"])
    arrays = {}
    for c in columns:
        vals = [r.get(c) for r in rows]
        present = [v for v in vals if v is not None]
        if present and all(isinstance(v, int) and not isinstance(v, bool) for v in present):
            arrays[c] = pa.array(vals, pa.int64())
        elif present and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
            arrays[c] = pa.array([None if v is None else float(v) for v in vals], pa.float64())
        else:
            arrays[c] = pa.array([None if v is None else str(v) for v in vals], pa.string())
    path = Path(path)
    pq.write_table(pa.table(arrays), path)
    return path
