"""Settings: one pydantic model per YAML section, merged from defaults, a file and ``--set`` overrides.

A run's settings file has one section per stage (``detect: {families: [tag36h11]}``) plus the
``rerun`` section shared by every stage. Unknown sections and keys are errors that name the file
and suggest the nearest valid name; a wrong value names the file, the key and what was expected.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from pipeline.errors import ConfigError
from pipeline.json_types import JSONObject


class SettingsModel(BaseModel):
    """Base of every settings model (each YAML section and the models nested in one).

    Unknown keys are errors, values are frozen, and no number may be infinite or NaN: a ``.inf`` or
    ``1e400`` in a settings file or after ``--set`` is rejected at load with one line naming the key,
    never carried into a stage (where it overflowed a time conversion, aborted Ceres or became a NaN
    entropy). Physical bounds (``le=``/``ge=``) are on the fields themselves.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _yaml_words(cls, data: Any) -> Any:
        """YAML reads an unquoted ``off`` / ``on`` (also ``no`` / ``yes``) as a boolean, so ``--set
        graph.noise_estimate=off`` or ``noise_estimate: off`` in a file reached a choice field as False. A choice field
        whose choices hold the word takes it back as the word."""
        if not isinstance(data, dict):
            return data
        out = dict(data)
        for key, value in data.items():
            info = cls.model_fields.get(key)
            if not isinstance(value, bool) or info is None:
                continue
            choices = [str(a) for a in _literal_choices(info.annotation)]
            for word in ("on", "yes", "true") if value else ("off", "no", "false"):
                if word in choices:
                    out[key] = word
                    break
        return out


def _literal_choices(annotation: Any) -> tuple[Any, ...]:
    """The values of a ``Literal[...]`` annotation, also inside a union (``bool | Literal["auto"]``); () for others."""
    if get_origin(annotation) is Literal:
        return get_args(annotation)
    return tuple(v for arg in get_args(annotation) for v in _literal_choices(arg))


class RecordingSettings(SettingsModel):
    """How stages draw into their Rerun recordings."""

    n_sigma: float = Field(3.0, gt=0, description="Covariance ellipsoids are drawn at this many standard deviations.")
    image_stride: int = Field(5, ge=1, description="Log every n-th camera frame to the recordings (1 = every frame).")
    scan_stride: int = Field(5, ge=1, description="Log every n-th laser scan to the recordings.")


SHARED_SECTIONS: dict[str, type[BaseModel]] = {"rerun": RecordingSettings}


class Settings:
    """The resolved settings of every section, by section name."""

    def __init__(self, sections: Mapping[str, BaseModel], sources: Mapping[str, str]) -> None:
        self.sections = dict(sections)
        self.sources = dict(sources)

    def __getitem__(self, section: str) -> BaseModel:
        return self.sections[section]

    @property
    def rerun(self) -> RecordingSettings:
        """The shared recording settings."""
        section = self.sections["rerun"]
        if not isinstance(section, RecordingSettings):
            raise TypeError(f"the rerun section holds a {type(section).__name__}, not RecordingSettings")
        return section

    def only(self, *names: str) -> Settings:
        """The sections ``names`` and the shared sections, nothing else (what one stage may read)."""
        keep = {*names, *SHARED_SECTIONS}
        return Settings(
            {n: m for n, m in self.sections.items() if n in keep},
            {k: v for k, v in self.sources.items() if k.split(".")[0] in keep},
        )

    def dump(self) -> dict[str, JSONObject]:
        """Every section as plain JSON-able data."""
        return {name: model.model_dump(mode="json") for name, model in self.sections.items()}


def _nearest(name: str, choices: Iterable[str]) -> str:
    match = difflib.get_close_matches(name, list(choices), n=1)
    return f" (did you mean {match[0]!r}?)" if match else f"; valid: {', '.join(sorted(choices))}"


def _parse_override(text: str) -> tuple[str, list[str], object]:
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected SECTION.KEY=VALUE, e.g. --set detect.tag_size_m=0.16")
    lhs, rhs = text.split("=", 1)
    parts = lhs.strip().split(".")
    if len(parts) < 2 or not all(parts):
        raise ConfigError(f"--set {text!r}: expected SECTION.KEY=VALUE, e.g. --set detect.tag_size_m=0.16")
    try:
        value = yaml.safe_load(rhs) if rhs.strip() else ""
    except yaml.YAMLError:
        value = rhs
    return parts[0].replace("-", "_"), parts[1:], value


def _allowed(model: type[BaseModel], key: str) -> str:
    """The range a number field accepts, as ``"; allowed: 0 < value <= 1000"`` (empty for other fields)."""
    info = model.model_fields.get(key)
    if info is None:
        return ""
    low = high = ""
    for bound in info.metadata:
        if (v := getattr(bound, "gt", None)) is not None:
            low = f"{v:g} < "
        elif (v := getattr(bound, "ge", None)) is not None:
            low = f"{v:g} <= "
        elif (v := getattr(bound, "lt", None)) is not None:
            high = f" < {v:g}"
        elif (v := getattr(bound, "le", None)) is not None:
            high = f" <= {v:g}"
    if info.annotation is not None and "float" in str(info.annotation) and not (low and high):
        low, high = low or "-inf < ", high or " < inf"  # finite, whatever the bounds
    return f"; allowed: {low}value{high}" if low or high else ""


def _describe(
    err: ValidationError, section: str, source_of: Mapping[tuple[str, str], str], model: type[BaseModel]
) -> str:
    first = err.errors()[0]
    loc = ".".join(str(p) for p in first["loc"])
    top = str(first["loc"][0]) if first["loc"] else ""
    source = source_of.get((section, top), "defaults")
    if first["type"] == "extra_forbidden":
        return f"{source}: unknown key {section}.{loc}"
    value = first.get("input")
    shown = f" (got {value!r})" if not isinstance(value, dict) else ""
    return f"{source}: {section}.{loc}: {first['msg'].rstrip('.')}{shown}{_allowed(model, top) if loc == top else ''}"


BASE_SOURCE = "run folder"
"""The source named for values that come from the ``base`` layer (a run folder's stored settings)."""


def load_settings(
    models: Mapping[str, type[BaseModel]],
    path: Path | None = None,
    overrides: Iterable[str] = (),
    base: Mapping[str, object] | None = None,
) -> Settings:
    """Resolve the settings of every section: defaults, then ``base``, then the file, then ``overrides``.

    Args:
        models: section name to settings model (stages first; ``rerun`` is added).
        path: optional YAML file with one mapping per section.
        overrides: ``SECTION.KEY=VALUE`` strings; values are parsed as YAML (``0.5``, ``[1, 2]``).
        base: settings stored earlier (a run folder's), section to key to value; keys that are no longer
            settings are left out.

    Raises:
        ConfigError: on a missing or malformed file, an unknown section or key, or a bad value.
    """
    models = {**models, **SHARED_SECTIONS}
    raw: dict[str, dict[str, Any]] = {name: {} for name in models}  # parsed YAML and JSON, validated below
    source_of: dict[tuple[str, str], str] = {}
    for section, values in (base or {}).items():
        if section in models and isinstance(values, Mapping):
            for k, v in values.items():
                if k in models[section].model_fields:
                    raw[section][k] = v
                    source_of[(section, k)] = BASE_SOURCE
    if path is not None:
        if not path.is_file():
            raise ConfigError(f"settings file {str(path)!r} not found; pass an existing YAML file to --config")
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as err:
            reason = "not UTF-8 text" if isinstance(err, UnicodeDecodeError) else (err.strerror or str(err))
            raise ConfigError(
                f"settings file {str(path)!r} cannot be read ({reason}); pass a YAML file to --config"
            ) from None
        try:
            loaded = yaml.safe_load(text) or {}
        except yaml.YAMLError as err:
            mark = getattr(err, "problem_mark", None)
            where = f" at line {mark.line + 1}" if mark is not None else ""
            raise ConfigError(f"{path}: not valid YAML{where}; fix the file or pass another") from None
        if not isinstance(loaded, dict):
            raise ConfigError(f"{path}: expected a mapping of sections (e.g. 'detect:'), got {type(loaded).__name__}")
        for section, values in loaded.items():
            key = str(section).replace("-", "_")
            if key not in models:
                raise ConfigError(f"{path}: unknown section {section!r}{_nearest(key, models)}")
            if not isinstance(values, dict):
                raise ConfigError(f"{path}: section {section!r} must be a mapping of keys, got {values!r}")
            for k, v in values.items():
                raw[key][str(k)] = v
                source_of[(key, str(k))] = str(path)
    for text in overrides:
        section, keys, value = _parse_override(text)
        if section not in models:
            raise ConfigError(f"--set {text!r}: unknown section {section!r}{_nearest(section, models)}")
        fields = models[section].model_fields
        if keys[0] not in fields:
            raise ConfigError(f"--set {text!r}: unknown key {section}.{keys[0]}{_nearest(keys[0], fields)}")
        target = raw[section]
        for k in keys[:-1]:
            target = target.setdefault(k, {})
        target[keys[-1]] = value
        source_of[(section, keys[0])] = "--set"
    sections: dict[str, BaseModel] = {}
    for name, model in models.items():
        for k in raw[name]:
            if k not in model.model_fields:
                src = source_of.get((name, k), "defaults")
                raise ConfigError(f"{src}: unknown key {name}.{k}{_nearest(k, model.model_fields)}")
        try:
            sections[name] = model.model_validate(raw[name])
        except ValidationError as err:
            raise ConfigError(_describe(err, name, source_of, model)) from None
    sources = {f"{s}.{k}": v for (s, k), v in source_of.items()}
    return Settings(sections, sources)


def defaults_yaml(models: Mapping[str, type[BaseModel]]) -> str:
    """``configs/default.yaml``: every key of every section with its default and its description."""
    models = {**models, **SHARED_SECTIONS}
    lines = [
        "# focusmap default settings: every key, its default, and what it means.",
        "# Generated from the settings models (focusmap show-config --defaults); a test fails on drift.",
        "# Copy the sections you change into your own file and pass it with --config,",
        "# or change one key with --set SECTION.KEY=VALUE.",
    ]
    for name, model in models.items():
        lines.append("")
        doc = (model.__doc__ or "").strip().splitlines()
        if doc:
            lines.append(f"# {doc[0]}")
        lines.append(f"{name}:")
        dumped = model().model_dump(mode="json")
        for key, info in model.model_fields.items():
            if info.description:
                lines.append(f"  # {info.description}")
            text = yaml.safe_dump({key: dumped[key]}, default_flow_style=True, sort_keys=False, width=1000)
            text = text.strip()
            if text.startswith("{") and text.endswith("}"):
                text = text[1:-1]
            lines.append(f"  {text}")
    return "\n".join(lines) + "\n"
