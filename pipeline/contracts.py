"""Typed artifact contracts: each file a stage writes is declared once, and read and written through it.

A stage declares its artifacts in one module (``stages/<stage>/artifacts.py``):

```python
STAMP_NS = Column("stamp_ns", pa.int64(), "bag clock, ns")
DETECTIONS = TableSpec("detections.parquet", "one row per tag seen in a frame", [FRAME, STAMP_NS, ...])
CAMERA = JsonSpec("camera.json", "the camera model", CameraModel)          # a pydantic model
STAGE_ARTIFACTS = ArtifactSet("detect", [DETECTIONS, ...])
```

and writes with ``DETECTIONS.write(ctx.output, columns)`` and reads with ``DETECTIONS.read(ctx.input("detect"))``.
A :class:`Column` is a ``str`` (its name), so ``table[STAMP_NS]`` and ``row[STAMP_NS]`` work as before;
it also carries its Arrow type and meaning. Writing casts to the declared schema and fails on a missing or
unknown column (a programming error); reading checks the declared columns are there and names the stage
to re-run when they are not (an old run folder). The documentation tables in ``docs/artifacts.md`` are
rendered from the same declarations (:func:`render_markdown`), and a test fails when they drift.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

import pyarrow as pa
import pyarrow.parquet as pq
from pydantic import BaseModel, ValidationError

from pipeline.artifacts import StageInput, StageOutput
from pipeline.errors import InputError
from pipeline.run_folder import write_json_atomic

M = TypeVar("M", bound=BaseModel)


class Column(str):
    """A column name that also knows its Arrow type and what it holds."""

    type: pa.DataType
    doc: str

    def __new__(cls, name: str, type_: pa.DataType, doc: str) -> Column:
        self = super().__new__(cls, name)
        self.type = type_
        self.doc = doc
        return self

    @property
    def field(self) -> pa.Field:
        """The Arrow field of the column."""
        return pa.field(str(self), self.type)


def _type_name(t: pa.DataType) -> str:
    if pa.types.is_fixed_size_list(t):
        return f"{t.list_size} × {_type_name(t.value_type)}"
    if pa.types.is_list(t) or pa.types.is_large_list(t):
        return f"list of {_type_name(t.value_type)}"
    return {"double": "float64", "float": "float32", "bool": "bool", "large_binary": "binary"}.get(str(t), str(t))


def _rerun_hint(stage: str) -> str:
    return f"re-run 'focusmap {stage.replace('_', '-')} RUN --force'"


@dataclass(frozen=True)
class TableSpec:
    """A Parquet table artifact: its file name, what a row is, and its columns in order."""

    file: str
    doc: str
    columns: tuple[Column, ...]
    optional: bool = False
    """Written only in some runs (e.g. when the bag holds detections)."""

    def __init__(self, file: str, doc: str, columns: Iterable[Column], optional: bool = False) -> None:
        object.__setattr__(self, "file", file)
        object.__setattr__(self, "doc", doc)
        object.__setattr__(self, "columns", tuple(columns))
        object.__setattr__(self, "optional", optional)
        names = [str(c) for c in self.columns]
        if len(set(names)) != len(names):
            raise ValueError(f"{file}: a column is declared twice: {names}")

    @property
    def schema(self) -> pa.Schema:
        """The Arrow schema of the table."""
        return pa.schema([c.field for c in self.columns])

    @property
    def names(self) -> list[str]:
        """Column names in order."""
        return [str(c) for c in self.columns]

    def table(self, data: pa.Table | Mapping[str, Any] | Sequence[Mapping[str, Any]]) -> pa.Table:
        """``data`` (a table, a dict of columns or a list of rows) as a table of exactly this schema.

        Raises:
            ValueError: a declared column is missing or an undeclared one is present (a bug in the writer).
        """
        if isinstance(data, pa.Table):
            given = set(data.column_names)
        elif isinstance(data, Mapping):
            given = set(data)
        else:
            given = set().union(*(r.keys() for r in data)) if data else set(self.names)
        missing, extra = set(self.names) - given, given - set(self.names)
        if missing or extra:
            raise ValueError(f"{self.file}: missing columns {sorted(missing)}, undeclared columns {sorted(extra)}")
        if isinstance(data, pa.Table):
            return data.select(self.names).cast(self.schema)
        if isinstance(data, Mapping):
            return pa.table({n: data[n] for n in self.names}, schema=self.schema)
        return pa.Table.from_pylist(list(data), schema=self.schema)

    def write(self, out: StageOutput, data: pa.Table | Mapping[str, Any] | Sequence[Mapping[str, Any]]) -> Path:
        """Write the table into the stage's output folder."""
        return out.write_table(self.file, self.table(data))

    def writer(self, path: Path) -> pq.ParquetWriter:
        """A streaming writer of this schema (for tables written in batches)."""
        return pq.ParquetWriter(path, self.schema, compression="zstd")

    def _checked(self, inp: StageInput, columns: Sequence[str] | None) -> tuple[Path, pa.Schema]:
        """The file and the schema of the wanted columns, once the file is known to hold them."""
        wanted = list(columns) if columns is not None else self.names
        unknown = [c for c in wanted if c not in self.names]
        if unknown:
            raise ValueError(f"{self.file} declares no columns {unknown}")
        path = inp.file(self.file)
        present = pq.read_schema(path)
        missing = [c for c in wanted if c not in present.names]
        if missing:
            raise InputError(f"{inp.stage}/{self.file} lacks columns {missing}; {_rerun_hint(inp.stage)}") from None
        return path, pa.schema([self.schema.field(c) for c in wanted])

    def _cast(self, inp: StageInput, data: pa.Table, schema: pa.Schema) -> pa.Table:
        try:
            return data.cast(schema)
        except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as err:
            raise InputError(
                f"{inp.stage}/{self.file} has columns of other types ({err}); {_rerun_hint(inp.stage)}"
            ) from None

    def read(self, inp: StageInput, columns: Sequence[str] | None = None) -> pa.Table:
        """Read the table (or some of its columns) from a finished stage, checked against the declaration.

        Raises:
            InputError: the file or a declared column is missing, or a column has another type (an old run).
        """
        path, schema = self._checked(inp, columns)
        return self._cast(inp, pq.read_table(path, columns=schema.names), schema)

    def batches(self, inp: StageInput, batch_size: int, columns: Sequence[str] | None = None) -> Iterator[pa.Table]:
        """The table in pieces of at most ``batch_size`` rows (for tables too large to hold, e.g. images), checked
        like :meth:`read`.

        Raises:
            InputError: as :meth:`read` (before the first piece is returned).
        """
        path, schema = self._checked(inp, columns)
        # pre_buffer (pyarrow's default) keeps what it read ahead: memory grew with every row group read, 740 MB
        # after 2,300 raw 640x480 frames against a flat 240 MB without it, which also reads them faster.
        return (
            self._cast(inp, pa.Table.from_batches([b]), schema)
            for b in pq.ParquetFile(path, pre_buffer=False).iter_batches(batch_size=batch_size, columns=schema.names)
        )

    def num_rows(self, inp: StageInput) -> int:
        """How many rows the finished stage's table has (from the file's metadata; nothing is read)."""
        return int(pq.ParquetFile(inp.file(self.file)).metadata.num_rows)

    def markdown(self) -> str:
        """The table's documentation: its rows and a line per column."""
        lines = [f"**`{self.file}`**{' (only in some runs)' if self.optional else ''}: {self.doc}", ""]
        lines += ["| column | type | meaning |", "| --- | --- | --- |"]
        lines += [f"| `{c}` | {_type_name(c.type)} | {c.doc} |" for c in self.columns]
        return "\n".join(lines)


@dataclass(frozen=True)
class JsonSpec(Generic[M]):
    """A JSON artifact whose content is a pydantic model."""

    file: str
    doc: str
    model: type[M]
    optional: bool = False

    def write(self, out: StageOutput, value: M) -> Path:
        """Write the model as JSON."""
        p = out.file(self.file)
        write_json_atomic(p, value.model_dump(mode="json"))
        return p

    def read(self, inp: StageInput) -> M:
        """Read and validate the JSON artifact of a finished stage.

        Raises:
            InputError: the file is missing, not JSON, or does not match the model (an old run).
        """
        path = inp.file(self.file)
        try:
            return self.model.model_validate(json.loads(path.read_text()))
        except (ValueError, ValidationError) as err:
            first = str(err).splitlines()[0]
            raise InputError(
                f"{inp.stage}/{self.file} is not what this version writes ({first}); {_rerun_hint(inp.stage)}"
            ) from None

    def markdown(self) -> str:
        """The file's documentation: a line per key of the model."""
        lines = [f"**`{self.file}`**{' (only in some runs)' if self.optional else ''}: {self.doc}", ""]
        lines += ["| key | type | meaning |", "| --- | --- | --- |"]
        for name, info in self.model.model_fields.items():
            ann = getattr(info.annotation, "__name__", None) or str(info.annotation).replace("typing.", "")
            cell = ann.replace("|", "\\|")  # a union type must not end the table cell
            lines.append(f"| `{name}` | {cell} | {info.description or ''} |")
        return "\n".join(lines)


@dataclass(frozen=True)
class FileSpec:
    """Any other artifact (arrays, text, figures): its name and what it holds."""

    file: str
    doc: str
    optional: bool = False

    def markdown(self) -> str:
        """One line: the file and its meaning."""
        return f"**`{self.file}`**{' (only in some runs)' if self.optional else ''}: {self.doc}"


Spec = TableSpec | JsonSpec[Any] | FileSpec


@dataclass(frozen=True)
class ArtifactSet:
    """Everything one stage writes into ``RUN/<stage>/``."""

    stage: str
    doc: str
    specs: tuple[Spec, ...]

    def __init__(self, stage: str, doc: str, specs: Iterable[Spec]) -> None:
        object.__setattr__(self, "stage", stage)
        object.__setattr__(self, "doc", doc)
        object.__setattr__(self, "specs", tuple(specs))

    def markdown(self) -> str:
        """The stage's section of ``docs/artifacts.md``."""
        parts = [f"## `{self.stage}/`", "", self.doc, ""]
        for spec in self.specs:
            parts += [spec.markdown(), ""]
        return "\n".join(parts)


def render_markdown(title: str, intro: str, sets: Iterable[ArtifactSet]) -> str:
    """A whole artifacts document: a title, an introduction and a section per stage."""
    body = [f"# {title}", "", intro.strip(), ""]
    for s in sets:
        body.append(s.markdown())
    return "\n".join(body).rstrip() + "\n"
