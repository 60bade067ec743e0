"""Batch files: the recordings of a batch, each with its run folder's name and its own settings.

A batch file lists one recording per entry, for fleets of rigs whose settings differ (tag size, camera
file, topics). It is YAML (a list of mappings, or a mapping whose ``recordings`` key holds that list)
or CSV (a header row, then one row per recording; ``#`` starts a comment line). The keys (YAML) or
columns (CSV) of an entry are:

- ``recording`` (required): the bag file or ROS 2 bag folder;
- ``name``: its run folder's name (default: chosen by :func:`pipeline.batch.run_names`);
- ``config``: a YAML settings file layered over the batch's ``--config`` and ``--set``;
- the input options of ``focusmap run``, by flag without the dashes (``camera``, ``start``, ``end``,
  ``stride``, ``salvage``, ``truth``: the options of the stages that read the recording and those other stages
  share with run, taken from the registry);
- ``SECTION.KEY``: any setting, as ``--set SECTION.KEY=VALUE`` takes it (``detect.tag_size_m``); in
  YAML a section may also be a nested mapping (``detect: {tag_size_m: 0.2}``).

An empty value (an empty CSV cell) leaves the key unset. Relative paths (recording, config, and path options
such as camera and truth) are relative to the batch file's folder. An entry's settings are the batch's
(defaults, ``--config``, ``--set`` and the command's options), then the entry's ``config``, then its options
and settings.

The whole file is checked when it is loaded, before anything runs: every problem (an unknown key, a
missing recording, a bad value, a duplicate name) is one line of :class:`BatchFileError`.
"""

from __future__ import annotations

import csv
import difflib
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from pipeline.config import SHARED_SECTIONS, Settings, load_settings
from pipeline.errors import ConfigError, InputError
from pipeline.registry import Registry
from pipeline.run_folder import check_run_name
from pipeline.stage import Option, run_options

RECORDING: Final = "recording"
NAME: Final = "name"
CONFIG: Final = "config"
_TRUE: Final = frozenset({"true", "yes", "on", "1"})
_FALSE: Final = frozenset({"false", "no", "off", "0"})


class BatchFileError(InputError):
    """Everything wrong with a batch (its file, its names): one problem per line, each printed as an ``error:`` line."""

    def __init__(self, problems: Sequence[str]) -> None:
        self.problems = list(problems)
        super().__init__("\nerror: ".join(self.problems))


@dataclass(frozen=True)
class BatchEntry:
    """One recording of a batch.

    Attributes:
        recording: the bag file or ROS 2 bag folder.
        name: its run folder's name; None: chosen from the recording's path (:func:`pipeline.batch.run_names`).
        settings: its settings; None: the batch's.
        where: where it was listed, for messages (``fleet.csv line 3``); empty for a command-line argument.
    """

    recording: Path
    name: str | None = None
    settings: Settings | None = None
    where: str = ""


def _options(registry: Registry) -> dict[str, list[tuple[str, Option]]]:
    """The options of ``focusmap run`` by entry key (``camera``, ``truth``): the options of the stages reading the
    source and those other stages share with run; a key several stages share sets the setting of each."""
    out: dict[str, list[tuple[str, Option]]] = {}
    for section, option in run_options(registry):
        out.setdefault(option.flag.lstrip("-"), []).append((section, option))
    return out


def _nearest(key: str, choices: Iterable[str]) -> str:
    match = difflib.get_close_matches(key, list(choices), n=1)
    return f" (did you mean {match[0]!r}?)" if match else ""


def _key_problem(key: str, registry: Registry) -> str | None:
    """What is wrong with an entry key (a YAML key, a CSV column), None for a known one."""
    plain = [RECORDING, NAME, CONFIG, *_options(registry)]
    if key in plain:
        return None
    if "." not in key:
        return f"unknown key {key!r}{_nearest(key, plain)}; valid: {', '.join(plain)} and SECTION.KEY settings"
    models = {**registry.models(), **SHARED_SECTIONS}
    section, name = key.split(".", 2)[:2]
    section = section.replace("-", "_")
    if section not in models:
        return f"unknown setting {key!r}: no section {section!r}{_nearest(section, models)}"
    if name not in models[section].model_fields:
        return f"unknown setting {key!r}{_nearest(name, models[section].model_fields)}"
    return None


def _path(value: object, folder: Path) -> Path:
    return folder / Path(str(value)).expanduser()


def _option_value(option: Option, value: object, folder: Path) -> object:
    """An entry's value for ``option``, as the type the command line gives it; ValueError says what is wrong."""
    kind = option.kind
    if kind is bool:
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower()
        if text not in _TRUE | _FALSE:
            raise ValueError(f"expected true or false, got {value!r}")
        return text in _TRUE
    if kind is Path:
        return _path(value, folder)
    if isinstance(value, bool):
        raise ValueError(f"expected a number, got {value!r}")
    try:
        number = kind(value)
    except (TypeError, ValueError):
        raise ValueError(f"expected {'a whole number' if kind is int else 'a number'}, got {value!r}") from None
    if option.min is not None and number < option.min:
        raise ValueError(f"must be at least {option.min:g}, got {value!r}")
    return number


def _set_text(key: str, value: object, from_text: bool) -> str:
    """``SECTION.KEY=VALUE`` for a setting: CSV text as ``--set`` takes it, a YAML value as its JSON (valid YAML)."""
    return f"{key}={value if from_text else json.dumps(value)}"


def _config_message(err: ConfigError, override: str) -> str:
    """A settings error without the ``--set`` framing (the value came from the batch file, not the command line)."""
    return str(err).removeprefix(f"--set {override!r}: ").removeprefix("--set: ")


def _flatten(raw: Mapping[Any, Any], sections: Iterable[str]) -> dict[str, object]:
    """YAML entry keys with nested sections (``detect: {tag_size_m: 0.2}``) as ``SECTION.KEY`` keys."""
    known = set(sections)
    flat: dict[str, object] = {}
    for key, value in raw.items():
        name = str(key)
        if name.replace("-", "_") in known and isinstance(value, Mapping):
            flat.update({f"{name}.{k}": v for k, v in value.items()})
        else:
            flat[name] = value
    return flat


def _entry(
    raw: Mapping[str, object],
    where: str,
    folder: Path,
    registry: Registry,
    base: Settings,
    from_text: bool,
    problems: list[str],
) -> BatchEntry | None:
    """One entry, checked; its problems are appended to ``problems`` (None when it has any)."""
    options = _options(registry)
    models = registry.models()
    given = {k: v for k, v in raw.items() if v is not None and not (isinstance(v, str) and not v.strip())}
    recording_text = given.get(RECORDING)
    label = f"{where} ({recording_text})" if recording_text is not None else where
    found: list[str] = []
    if recording_text is None:
        found.append(f"no {RECORDING!r}; every entry names the bag file or ROS 2 bag folder it runs")
        recording = None
    else:
        recording = _path(recording_text, folder)
        if not recording.exists():
            found.append(f"recording {str(recording)!r} does not exist")
    name = None
    if NAME in given:
        try:
            name = check_run_name(str(given[NAME]))
        except InputError:
            found.append(f"name {str(given[NAME])!r} is not a plain folder name (no '/', not '.' or '..')")
    config = None
    if CONFIG in given:
        config = _path(given[CONFIG], folder)
        if not config.is_file():
            found.append(f"settings file {str(config)!r} not found")
    overrides: list[str] = []
    base_values = base.dump()
    for key, value in given.items():
        if key in (RECORDING, NAME, CONFIG):
            continue
        if key in options:
            for section, option in options[key]:
                try:
                    override = option.override(section, _option_value(option, value, folder))
                except (ValueError, InputError) as err:
                    found.append(f"{key}: {err}")
                    break
                if override is not None:
                    overrides.append(override)
            continue
        problem = _key_problem(key, registry)
        if problem is not None:
            found.append(problem)
            continue
        override = _set_text(key, value, from_text)
        try:
            load_settings(models, None, [override], base=base_values)
        except ConfigError as err:
            found.append(_config_message(err, override))
            continue
        overrides.append(override)
    settings = None
    if not found and (config is not None or overrides):
        try:
            settings = load_settings(models, config, overrides, base=base_values)
        except ConfigError as err:
            found.append(str(err))
    problems.extend(f"{label}: {text}" for text in found)
    if recording is None:
        return None
    return BatchEntry(recording, name if isinstance(name, str) else None, settings, where)


def _read_yaml(path: Path, sections: Iterable[str]) -> list[tuple[str, Mapping[str, object]]]:
    import yaml

    try:
        loaded = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise BatchFileError([f"{path}: not valid YAML{where}"]) from None
    if isinstance(loaded, dict):
        unknown = [str(k) for k in loaded if k != "recordings"]
        if unknown:
            raise BatchFileError(
                [f"{path}: unknown top-level key {k!r}; the file holds 'recordings:'" for k in unknown]
            )
        loaded = loaded.get("recordings")
    if not isinstance(loaded, list):
        raise BatchFileError([f"{path}: expected a list of recordings (or 'recordings:' with one), one mapping each"])
    entries: list[tuple[str, Mapping[str, object]]] = []
    problems = []
    for i, item in enumerate(loaded, start=1):
        if not isinstance(item, dict):
            problems.append(f"{path.name} entry {i}: expected a mapping (recording: ..., name: ...), got {item!r}")
            continue
        entries.append((f"{path.name} entry {i}", _flatten(item, sections)))
    if problems:
        raise BatchFileError(problems)
    return entries


def _read_csv(path: Path, registry: Registry) -> list[tuple[str, Mapping[str, object]]]:
    with path.open(newline="") as f:
        rows = [(n, row) for n, row in enumerate(csv.reader(f), start=1) if row and not row[0].lstrip().startswith("#")]
    if not rows:
        raise BatchFileError([f"{path}: empty; the first row names the columns (recording,name,...)"])
    (_, header), *body = rows
    header = [h.strip() for h in header]
    problems = [
        f"{path}: column {h!r} appears more than once" for h in sorted({h for h in header if header.count(h) > 1})
    ]
    if RECORDING not in header:
        problems.append(f"{path}: no {RECORDING!r} column; the first row names the columns (recording,name,...)")
    problems += [f"{path}: column {h!r}: {p}" for h in dict.fromkeys(header) if (p := _key_problem(h, registry))]
    if problems:
        raise BatchFileError(problems)
    entries: list[tuple[str, Mapping[str, object]]] = []
    for line, row in body:
        if len(row) > len(header):
            problems.append(f"{path.name} line {line}: {len(row)} cells but {len(header)} columns")
            continue
        entries.append((f"{path.name} line {line}", dict(zip(header, (c.strip() for c in row), strict=False))))
    if problems:
        raise BatchFileError(problems)
    return entries


def read_batch_file(path: Path, registry: Registry, base: Settings) -> tuple[list[BatchEntry], list[str]]:
    """The entries of a batch file (``.yaml``/``.yml`` or ``.csv``) and its problems, one line each.

    An entry with problems is returned too (with the batch's settings) when it names a recording, so that the run
    folder names of the whole batch can be checked before anything is reported
    (:func:`pipeline.batch.plan_tasks` takes these problems and adds those of the names).

    Args:
        path: the batch file.
        registry: the stages (their settings models; the options of those reading the source).
        base: the batch's settings, under each entry's own.

    Raises:
        InputError: when the file cannot be read as a whole (missing, not YAML or CSV, no recordings);
            :class:`BatchFileError` for several such problems.
    """
    if not path.is_file():
        raise InputError(f"batch file {str(path)!r} not found; pass an existing .yaml or .csv file")
    suffix = path.suffix.lower()
    try:
        if suffix in (".yaml", ".yml"):
            raw = _read_yaml(path, registry.models())
            from_text = False
        elif suffix == ".csv":
            raw = _read_csv(path, registry)
            from_text = True
        else:
            raise InputError(f"batch file {str(path)!r}: expected a .yaml, .yml or .csv file")
    except (OSError, UnicodeDecodeError) as err:
        reason = "not UTF-8 text" if isinstance(err, UnicodeDecodeError) else (err.strerror or str(err))
        raise InputError(f"batch file {str(path)!r} cannot be read ({reason})") from None
    if not raw:
        raise InputError(f"batch file {str(path)!r} lists no recordings")
    folder = path.resolve().parent
    problems: list[str] = []
    entries = [_entry(item, where, folder, registry, base, from_text, problems) for where, item in raw]
    return [e for e in entries if e is not None], problems


def load_batch_file(path: Path, registry: Registry, base: Settings) -> list[BatchEntry]:
    """The entries of a batch file, every one checked (:func:`read_batch_file`).

    Raises:
        BatchFileError: every problem of the file, one per line, before anything runs.
    """
    entries, problems = read_batch_file(path, registry, base)
    if problems:
        raise BatchFileError(problems)
    return entries
