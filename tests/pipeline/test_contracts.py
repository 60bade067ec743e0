"""Artifact contracts: tables and JSON written and read back through their declarations."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from pydantic import BaseModel

from pipeline.artifacts import StageInput, StageOutput
from pipeline.contracts import ArtifactSet, Column, JsonSpec, TableSpec
from pipeline.errors import InputError

A = Column("a", pa.int64(), "an integer")
B = Column("b", pa.list_(pa.float64(), 2), "a pair")
SPEC = TableSpec("t.parquet", "a test table", [A, B])


class Doc(BaseModel):
    n: int
    name: str = "x"
    note: str | None = None


DOC = JsonSpec("doc.json", "a test document", Doc)


def test_a_column_is_its_name() -> None:
    assert A == "a" and {"a": 1}[A] == 1 and A.type == pa.int64()


def test_table_round_trip_casts_to_the_declared_schema(tmp_path: Path) -> None:
    SPEC.write(StageOutput(tmp_path), {"b": [[1.0, 2.0], [3.0, 4.0]], "a": [1, 2]})  # order and int width fixed
    assert pq.read_schema(tmp_path / "t.parquet").names == ["a", "b"]
    back = SPEC.read(StageInput("demo", tmp_path))
    assert back.schema == SPEC.schema
    assert back.column(A).to_pylist() == [1, 2]
    assert SPEC.read(StageInput("demo", tmp_path), columns=[B]).column_names == ["b"]


def test_rows_and_tables_write_the_same(tmp_path: Path) -> None:
    rows = [{"a": 1, "b": [0.5, 1.5]}]
    assert SPEC.table(rows).equals(SPEC.table(pa.table({"a": [1], "b": [[0.5, 1.5]]})))


def test_writing_a_wrong_set_of_columns_is_a_bug(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"missing columns \['b'\]"):
        SPEC.write(StageOutput(tmp_path), {"a": [1]})
    with pytest.raises(ValueError, match=r"undeclared columns \['c'\]"):
        SPEC.write(StageOutput(tmp_path), {"a": [1], "b": [[1.0, 2.0]], "c": [0]})


def test_reading_an_old_table_names_the_stage_to_rerun(tmp_path: Path) -> None:
    pq.write_table(pa.table({"a": [1]}), tmp_path / "t.parquet")
    with pytest.raises(InputError, match=r"demo/t.parquet lacks columns \['b'\]; re-run 'focusmap demo RUN --force'"):
        SPEC.read(StageInput("demo", tmp_path))
    pq.write_table(pa.table({"a": ["not a number"], "b": [[1.0, 2.0]]}), tmp_path / "t.parquet")
    with pytest.raises(InputError, match="other types"):
        SPEC.read(StageInput("demo", tmp_path))


def test_json_round_trip_and_validation(tmp_path: Path) -> None:
    DOC.write(StageOutput(tmp_path), Doc(n=3))
    assert DOC.read(StageInput("demo", tmp_path)) == Doc(n=3, name="x")
    (tmp_path / "doc.json").write_text('{"name": "y"}')
    with pytest.raises(InputError, match=r"doc\.json is not what this version writes"):
        DOC.read(StageInput("demo", tmp_path))


def test_markdown_lists_every_column_and_key() -> None:
    text = ArtifactSet("demo", "Test stage.", [SPEC, DOC]).markdown()
    needles = ("`t.parquet`", "| `a` | int64 | an integer |", "| `b` | 2 × float64 | a pair |", "| `n` | int |")
    assert "| `note` | str \\| None |" in text
    for needle in needles:
        assert needle in text


def test_a_table_read_in_batches_is_checked_and_cast(tmp_path: Path) -> None:
    SPEC.write(StageOutput(tmp_path), {"a": [1, 2, 3], "b": [[1.0, 2.0]] * 3})
    inp = StageInput("demo", tmp_path)
    pieces = list(SPEC.batches(inp, batch_size=2, columns=[A]))
    assert [p.column(A).to_pylist() for p in pieces] == [[1, 2], [3]]
    assert SPEC.num_rows(inp) == 3
    pq.write_table(pa.table({"a": [1]}), tmp_path / "t.parquet")
    with pytest.raises(InputError, match=r"lacks columns \['b'\]"):
        SPEC.batches(inp, batch_size=2)
