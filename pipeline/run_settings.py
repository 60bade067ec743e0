"""A run folder keeps the settings it was made with: later commands start from them, and say what they change.

``RUN/settings.json`` holds, per section, the settings of the last run of that section's stage (and the shared
sections). A later command on the folder resolves its settings with those as the base layer under ``--config``
and ``--set`` (:func:`resolve_run_settings`), so a second ``focusmap run`` without the first one's ``--set``
does not silently recompute with the defaults. What differs from the stored settings is printed, one line per
key, and so is a short line when stored non-default values are being kept. ``reset`` starts from the defaults.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path

from pydantic import BaseModel

from pipeline.config import BASE_SOURCE, SHARED_SECTIONS, Settings, load_settings
from pipeline.json_types import JSONObject
from pipeline.run_folder import write_json_atomic

SETTINGS_FILE = "settings.json"


def stored_settings(run_dir: Path) -> JSONObject | None:
    """The settings a run folder keeps (None: none stored, or not a run folder yet)."""
    path = Path(run_dir) / SETTINGS_FILE
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except ValueError:
        return None
    return data if isinstance(data, dict) else None


def _show(value: object) -> str:
    return json.dumps(value, sort_keys=True)


def resolve_run_settings(
    models: Mapping[str, type[BaseModel]],
    run_dir: Path | None,
    config: Path | None = None,
    overrides: Iterable[str] = (),
    reset: bool = False,
    running: Iterable[str] | None = None,
) -> tuple[Settings, list[str]]:
    """Settings for a command on ``run_dir``, and the lines that say how they differ from the stored ones.

    Args:
        models: section name to settings model.
        run_dir: the run folder (it may not exist yet: then there is nothing stored).
        config, overrides: ``--config`` and ``--set``, applied on top of the stored settings.
        reset: start from the defaults instead of the stored settings (the differences are still printed).
        running: the stages this command runs; a changed key of another stage's section is said not to be used.

    Returns:
        The settings and the lines to print (``settings: select_landmarks.budget 30 -> 3 (--set)``).
    """
    stored = stored_settings(run_dir) if run_dir is not None else None
    settings = load_settings(models, config, list(overrides), base=None if reset else stored)
    if stored is None:
        return settings, []
    lines = ["settings: starting from the defaults (--reset-settings), not the run folder's"] if reset else []
    run_set = None if running is None else {*running, *SHARED_SECTIONS}
    now = settings.dump()
    for section, values in now.items():
        before = stored.get(section)
        if not isinstance(before, dict):
            continue
        for key, value in values.items():
            if key not in before or before[key] == value:
                continue
            source = settings.sources.get(f"{section}.{key}", "defaults")
            line = f"settings: {section}.{key} {_show(before[key])} -> {_show(value)} ({source})"
            if run_set is not None and section not in run_set:
                line += f"; not used: this command does not run {section.replace('_', '-')}"
            lines.append(line)
    kept = []
    all_models = {**models, **SHARED_SECTIONS}
    for key, source in sorted(settings.sources.items()):
        section, name = key.split(".", 1)
        if source != BASE_SOURCE:
            continue
        default = all_models[section]().model_dump(mode="json").get(name)
        if now[section][name] != default:
            kept.append(f"{key}={_show(now[section][name])}")
    if kept:
        shown = ", ".join(kept[:4]) + (f" and {len(kept) - 4} more (see settings.json)" if len(kept) > 4 else "")
        lines.append(f"settings: keeping the run folder's {shown}; --reset-settings starts from the defaults")
    return settings, lines


def store_run_settings(run_dir: Path, settings: Settings, sections: Iterable[str]) -> None:
    """Record the settings ``sections`` ran with (and the shared sections) in ``RUN/settings.json``.

    The other sections keep what is stored: they describe the artifacts of stages this command did not run.
    Call it holding the run folder's lock (:func:`pipeline.run_folder.run_folder_lock`). Nothing is written
    when nothing changes, so a command whose stages are all up to date leaves the folder as it was.
    """
    before = stored_settings(run_dir)
    stored = dict(before or {})
    now = settings.dump()
    for section in (*sections, *SHARED_SECTIONS):
        if section in now:
            stored[section] = now[section]
    for section, values in now.items():  # first time: every section, so the folder starts complete
        stored.setdefault(section, values)
    if stored != before:
        write_json_atomic(Path(run_dir) / SETTINGS_FILE, stored)
