"""Fixtures every test folder may use: the third-party test data, and whether a headless viewer can draw here."""

from __future__ import annotations

import os

# One BLAS thread, set before numpy loads: the tests' matrices are small (tens to hundreds of rows), where
# OpenBLAS's threads cost more in hand-offs than they save, and on a busy 2-core machine they wait for each
# other (a 150x150 inverse: 0.7 ms with one thread, 3.5 ms with two). A value set by the caller wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from pathlib import Path

import pytest

from tests.fixtures.shared_data import need_shared
from tests.fixtures.viewer import headless_viewer_problem


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (real recordings from other projects); tests skip where a clone has none."""
    return need_shared()


@pytest.fixture(scope="session")
def viewer_problem(tmp_path_factory: pytest.TempPathFactory) -> str | None:
    """Why Rerun's headless viewer cannot draw here (no Vulkan driver, so no render context), or None where it can;
    probed once per session by asking the bare viewer for a picture."""
    return headless_viewer_problem(tmp_path_factory.mktemp("viewer_probe"))


@pytest.fixture(scope="session")
def headless_viewer(viewer_problem: str | None) -> None:
    """Skips, with the viewer's own message, where Rerun's headless viewer cannot draw."""
    if viewer_problem is not None:
        pytest.skip(f"no picture from a headless viewer here (needs a Vulkan driver): {viewer_problem}")
