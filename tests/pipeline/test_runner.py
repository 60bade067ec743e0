"""Runner and run folder: skipping, forcing, atomic replacement, recovery after a kill."""

from __future__ import annotations

import gc
import json
import os
import signal
import subprocess
import sys
import textwrap
import weakref
from pathlib import Path

import pytest
from pydantic import BaseModel, ConfigDict, Field

from pipeline.config import load_settings
from pipeline.errors import StageError
from pipeline.registry import Registry
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from pipeline.stage import Stage

CALLS: list[str] = []


class ACfg(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    value: int = Field(1, description="A number.")
    fail: bool = Field(False, description="Raise half-way.")


def run_a(ctx, cfg: ACfg) -> dict:
    CALLS.append("a")
    ctx.output.write_json("a.json", {"value": cfg.value})
    if cfg.fail:
        raise StageError("asked to fail")
    return {"value": cfg.value}


def run_b(ctx, cfg: ACfg) -> dict:
    CALLS.append("b")
    a = ctx.input("a").read_json("a.json")
    ctx.output.write_json("b.json", {"twice": 2 * a["value"]})
    return {"twice": 2 * a["value"]}


REG = Registry(
    [
        Stage(name="a", config_type=ACfg, run=run_a),
        Stage(name="b", config_type=ACfg, run=run_b, inputs=("a",)),
    ]
)


@pytest.fixture
def run(tmp_path: Path) -> RunFolder:
    CALLS.clear()
    return RunFolder.create(tmp_path / "r", None)


def settings(*sets: str):
    return load_settings(REG.models(), None, list(sets))


def test_runs_then_skips_then_reruns_on_change(run: RunFolder) -> None:
    assert run_stage(run, REG, "a", settings()).status == "done"
    assert run_stage(run, REG, "b", settings()).status == "done"
    assert run_stage(run, REG, "a", settings()).status == "skipped"
    assert run_stage(run, REG, "b", settings()).status == "skipped"
    assert CALLS == ["a", "b"]
    # a new setting for a re-runs a; b's input fingerprint changed, so b re-runs too
    assert run_stage(run, REG, "a", settings("a.value=5")).status == "done"
    assert run_stage(run, REG, "b", settings("a.value=5")).status == "done"
    assert json.loads((run.path / "b" / "b.json").read_text()) == {"twice": 10}
    assert run_stage(run, REG, "b", settings("a.value=5"), force=True).status == "done"
    assert CALLS == ["a", "b", "a", "b", "b"]
    manifest = json.loads((run.path / "manifest.json").read_text())
    entry = manifest["stages"]["b"]
    assert entry["summary"]["twice"] == 10 and entry["inputs"]["a"] == manifest["stages"]["a"]["fingerprint"]
    assert entry["versions"]["gtsam"] and entry["versions"]["rerun-sdk"].startswith("0.41")
    assert (run.path / "a.rrd").is_file() and (run.path / "b.rrd").is_file()


def test_failure_keeps_previous_results_whole(run: RunFolder) -> None:
    run_stage(run, REG, "a", settings("a.value=3"))
    before = (run.path / "a" / "a.json").read_text()
    with pytest.raises(StageError):
        run_stage(run, REG, "a", settings("a.value=4", "a.fail=true"))
    assert (run.path / "a" / "a.json").read_text() == before
    assert not (run.path / ".partial").exists()
    assert json.loads((run.path / "manifest.json").read_text())["stages"]["a"]["summary"] == {
        "value": 3,
        "seconds": json.loads((run.path / "a" / "summary.json").read_text())["seconds"],
    }


def test_missing_input_names_the_command_to_run(run: RunFolder) -> None:
    with pytest.raises(StageError, match=r"needs 'a'.*run 'focusmap a "):
        run_stage(run, REG, "b", settings())


def test_recover_after_kill_restores_old_and_drops_partial(run: RunFolder) -> None:
    run_stage(run, REG, "a", settings())
    # what a kill between the two renames of a commit leaves: the old folder parked, the new half-written
    part = run.path / ".partial"
    part.mkdir()
    os.replace(run.path / "a", part / "a.old")
    (part / "b").mkdir()
    (part / "b" / "junk").write_text("x")
    again = RunFolder(run.path)
    assert part.exists()  # opening to read changes nothing: it may be another process's stage in progress
    with again.lock():
        assert (again.path / "a" / "a.json").is_file()
        assert not part.exists()


def test_killed_process_leaves_no_half_written_stage(tmp_path: Path) -> None:
    """A real SIGKILL in the middle of a stage: the previous output survives, the next run recovers."""
    script = tmp_path / "slow.py"
    script.write_text(
        textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(Path(__file__).resolve().parents[2])!r})
        from pydantic import BaseModel, ConfigDict
        from pipeline.config import load_settings
        from pipeline.registry import Registry
        from pipeline.run_folder import RunFolder
        from pipeline.runner import run_stage
        from pipeline.stage import Stage

        class C(BaseModel):
            model_config = ConfigDict(extra="forbid")
            slow: bool = False

        def go(ctx, cfg):
            ctx.output.write_json("out.json", {{"slow": cfg.slow}})
            if cfg.slow:
                print("started", flush=True)
                time.sleep(60)
            return {{}}

        reg = Registry([Stage(name="s", config_type=C, run=go)])
        run = RunFolder.create(__import__("pathlib").Path(sys.argv[1]), None)
        run_stage(run, reg, "s", load_settings(reg.models(), None, sys.argv[2:]))
    """)
    )
    rdir = tmp_path / "run"
    subprocess.run([sys.executable, str(script), str(rdir)], check=True)
    proc = subprocess.Popen([sys.executable, str(script), str(rdir), "s.slow=true"], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "started"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert json.loads((rdir / "s" / "out.json").read_text()) == {"slow": False}
    assert (rdir / ".partial" / "s").exists()  # the unfinished scratch output, never taken for a result
    with RunFolder(rdir).lock():  # free again: the kernel released the killed process's lock
        assert not (rdir / ".partial").exists()


class _Node:
    """An object in a reference cycle: only the cyclic collector frees it."""

    def __init__(self) -> None:
        self.me = self


def test_a_stage_starts_with_earlier_garbage_collected_and_what_lives_frozen(run: RunFolder) -> None:
    # the runner freezes the objects alive when a stage starts (its libraries), so that the collections during the
    # stage skip them; garbage left from before must be collected first, not frozen, and the stage's own cycles
    # must still be collected
    seen: dict[str, object] = {}

    def run_c(ctx, cfg: ACfg) -> dict:
        seen["earlier_freed"] = earlier() is None
        seen["frozen"] = gc.get_freeze_count()
        mine = weakref.ref(_Node())
        gc.collect()
        seen["own_freed"] = mine() is None
        return {}

    registry = Registry([Stage(name="c", config_type=ACfg, run=run_c)])
    gc.disable()  # no automatic collection between making the garbage and the stage
    try:
        earlier = weakref.ref(_Node())
        assert earlier() is not None
        assert run_stage(run, registry, "c", load_settings(registry.models(), None, [])).status == "done"
    finally:
        gc.enable()
        gc.unfreeze()
    assert seen["earlier_freed"] is True  # collected before the freeze, not kept in the frozen generation
    assert seen["own_freed"] is True  # the stage's own cycles are still collected
    frozen = seen["frozen"]
    assert isinstance(frozen, int) and frozen > 1000  # at least the modules pytest imported


def test_a_stage_whose_code_cannot_be_imported_leaves_nothing_behind(run: RunFolder) -> None:
    # the runner imports the stage's module before it runs it (to freeze its libraries): an import that fails there
    # is the stage's failure like any other, with its scratch folder and recording removed
    from pipeline.lazy import lazy

    registry = Registry([Stage(name="c", config_type=ACfg, run=lazy("tests.no_such_module_here:run"))])
    before = sorted(p.name for p in run.path.iterdir())
    with pytest.raises(ModuleNotFoundError):
        run_stage(run, registry, "c", load_settings(registry.models(), None, []))
    assert sorted(p.name for p in run.path.iterdir() if not p.name.startswith("error")) == before
    assert run.stage_entry("c") is None
