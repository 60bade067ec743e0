"""Fixtures of the stage tests: run folders that several test modules read."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.fixtures.office import prepare_office_run


@pytest.fixture(scope="session")
def office_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The office sample through ingest, detect and graph, once per session. Read it; to run stages, copy it
    (:func:`tests.fixtures.office.copy_run`)."""
    return prepare_office_run(tmp_path_factory.mktemp("office"))
