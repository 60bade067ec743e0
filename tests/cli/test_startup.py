"""The command line starts without the numerics: --help, info and show-config import no estimation, vision,
recording or table library (which take seconds to import); a stage's code is imported when it runs."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("gtsam", "rerun", "scipy", "cv2", "pycolmap", "pyarrow", "matplotlib")
BAG = ROOT / "sample_data" / "office" / "office.bag"

# Runs the command line in this interpreter as the console script would, then prints the heavy modules loaded.
PROBE = """
import json, sys
argv, heavy = json.loads(sys.argv[1]), json.loads(sys.argv[2])
if argv is None:
    import cli.app
else:
    from cli.app import main
    sys.argv = ["focusmap", *argv]
    try:
        main()
    except SystemExit as exit:
        assert exit.code in (0, None), exit.code
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in heavy)), file=sys.stderr)
"""


def _heavy_modules_after(argv: list[str] | None) -> list[str]:
    """The heavy modules in ``sys.modules`` of a fresh interpreter after it ran ``focusmap ARGV`` (None: imported
    ``cli.app`` only)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, json.dumps(argv), json.dumps(HEAVY)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stderr.strip().splitlines()[-1])


@pytest.mark.parametrize(
    "argv",
    [
        None,
        ["--help"],
        ["select-landmarks", "--help"],
        ["run", "--help"],
        ["show-config"],
        ["show-config", "--defaults"],
        ["info", str(BAG)],
    ],
    ids=lambda a: "import" if a is None else " ".join(a).replace(str(BAG), "BAG"),
)
def test_the_command_line_starts_without_the_numerics(argv: list[str] | None) -> None:
    assert _heavy_modules_after(argv) == []


def test_the_probe_sees_heavy_imports() -> None:
    """The control: the same probe reports a stage's code once something imports it."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    code = PROBE.replace("import cli.app", "import cli.app, stages.optimize.stage")
    proc = subprocess.run(
        [sys.executable, "-c", code, "null", json.dumps(HEAVY)], capture_output=True, text=True, env=env, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert "gtsam" in json.loads(proc.stderr.strip().splitlines()[-1])


STAGE_PACKAGES = [
    "stages.ingest",
    "stages.detect",
    "stages.graph",
    "stages.select_landmarks",
    "stages.select_measurements",
    "stages.optimize",
    "stages.evaluate",
]


@pytest.mark.parametrize("package", STAGE_PACKAGES)
def test_every_public_name_of_a_stage_package_resolves(package: str) -> None:
    """The names a stage package offers (imported on first use) are there, and its run function is its stage's."""
    module = importlib.import_module(package)
    for name in module.__all__:
        assert getattr(module, name) is not None, name
    run = module.STAGE.run
    assert run.__module__ == f"{package}.stage"
    assert run.target is importlib.import_module(run.__module__).run  # type: ignore[attr-defined]
    with pytest.raises(AttributeError):
        module.no_such_name  # noqa: B018
