"""Reading and writing a stage's artifacts: Parquet tables, JSON, ``.npy`` and ``.npz`` arrays."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.errors import InputError
from pipeline.run_folder import write_json_atomic


class StageOutput:
    """The scratch folder a running stage writes into (renamed into place when it finishes)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def file(self, name: str) -> Path:
        """A path inside the output folder (parents created)."""
        p = self.path / name
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def write_table(self, name: str, table: pa.Table | dict[str, npt.ArrayLike]) -> Path:
        """Write a Parquet table (a pyarrow Table or a dict of columns)."""
        if isinstance(table, dict):
            table = pa.table(table)
        p = self.file(name)
        pq.write_table(table, p, compression="zstd")
        return p

    def write_json(self, name: str, data: object) -> Path:
        """Write JSON (numpy arrays become lists)."""
        p = self.file(name)
        write_json_atomic(p, data)
        return p

    def write_npy(self, name: str, array: np.ndarray) -> Path:
        """Write one dense array."""
        p = self.file(name)
        np.save(p, np.asarray(array))
        return p

    def write_npz(self, name: str, **arrays: np.ndarray) -> Path:
        """Write named arrays."""
        p = self.file(name)
        # numpy's stub lets a **mapping also fill the bool ``allow_pickle``, so it rejects any dict of arrays
        np.savez_compressed(p, **arrays)  # type: ignore[arg-type]
        return p

    def write_text(self, name: str, text: str) -> Path:
        """Write a text file."""
        p = self.file(name)
        p.write_text(text)
        return p


class StageInput:
    """The finished artifacts of an upstream stage."""

    def __init__(self, stage: str, path: Path) -> None:
        self.stage = stage
        self.path = path

    def _require(self, name: str) -> Path:
        p = self.path / name
        if not p.exists():
            raise InputError(f"{self.stage} artifact {name!r} missing in {self.path}; re-run 'focusmap {self.stage}'")
        return p

    def exists(self, name: str) -> bool:
        """Whether the artifact is present."""
        return (self.path / name).exists()

    def file(self, name: str) -> Path:
        """Path of an artifact that must exist."""
        return self._require(name)

    def read_table(self, name: str, columns: list[str] | None = None) -> pa.Table:
        """Read a Parquet table."""
        return pq.read_table(self._require(name), columns=columns)

    def read_json(self, name: str) -> Any:
        """Read a JSON artifact (as ``json.loads`` returns it: the caller checks its shape)."""
        return json.loads(self._require(name).read_text())

    def read_npy(self, name: str) -> np.ndarray:
        """Read one dense array."""
        return np.load(self._require(name))

    def read_npz(self, name: str) -> dict[str, np.ndarray]:
        """Read named arrays."""
        with np.load(self._require(name)) as data:
            return {k: data[k] for k in data.files}

    @property
    def summary(self) -> dict[str, Any]:
        """The upstream stage's summary."""
        return self.read_json("summary.json")
