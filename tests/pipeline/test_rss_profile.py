"""tests/benchmarks/rss_profile.py runs a focusmap command in process and says where its memory peaked."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "tests" / "benchmarks" / "rss_profile.py"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/statm")
def test_the_peak_window_names_the_command_that_held_the_memory(tmp_path: Path) -> None:
    # a stage-like command that holds 200 MB for a moment: the highest window's stack must end in it
    out = tmp_path / "profile.txt"
    code = (
        "import runpy, sys, time, numpy as np\n"
        "import cli.app\n"
        "def hold():\n"
        "    a = np.ones(25 * 2**20)\n"
        "    time.sleep(0.3)\n"
        "    return float(a[-1])\n"
        "cli.app.main = hold\n"
        f"sys.argv = ['rss_profile.py', {str(out)!r}, 'anything']\n"
        f"runpy.run_path({str(SCRIPT)!r}, run_name='__main__')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    text = out.read_text()
    first_peak = text.split("PEAK", 2)[1]
    mib = float(first_peak.split()[2])
    assert mib > 200, text
    assert first_peak.strip().splitlines()[-1].endswith(" hold"), text
    assert "peak" in done.stderr


def test_without_a_command_it_prints_its_usage_and_fails() -> None:
    done = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, check=False)
    assert done.returncode != 0
    assert "rss_profile.py OUT.txt evaluate RUN" in done.stderr
