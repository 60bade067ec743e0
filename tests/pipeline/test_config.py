"""Settings: merging, validation and the messages a user sees."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import BaseModel, ConfigDict, Field

from pipeline.config import defaults_yaml, load_settings
from pipeline.errors import ConfigError
from stages import REGISTRY


class Toy(BaseModel):
    """A toy stage's settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    budget: int = Field(30, ge=0, description="How many to keep.")
    family: str = Field("tag36h11", description="Tag family.")


MODELS = {"toy": Toy}


def test_defaults_then_file_then_set(tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("toy:\n  budget: 10\n  family: tag25h9\n")
    s = load_settings(MODELS, cfg, ["toy.budget=12"])
    assert s["toy"].budget == 12 and s["toy"].family == "tag25h9"
    assert s.sources["toy.budget"] == "--set" and s.sources["toy.family"] == str(cfg)
    assert s.rerun.n_sigma == 3.0


def test_unknown_key_in_file_names_file_key_and_suggestion(tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("toy:\n  budgte: 10\n")
    with pytest.raises(ConfigError) as err:
        load_settings(MODELS, cfg)
    msg = str(err.value)
    assert str(cfg) in msg and "toy.budgte" in msg and "budget" in msg and "\n" not in msg


def test_unknown_section_and_set_key() -> None:
    with pytest.raises(ConfigError, match=r"unknown section 'tyo'.*'toy'"):
        load_settings(MODELS, None, ["tyo.budget=1"])
    with pytest.raises(ConfigError, match=r"--set 'toy.famly=x': unknown key toy.famly \(did you mean 'family'"):
        load_settings(MODELS, None, ["toy.famly=x"])
    with pytest.raises(ConfigError, match=r"expected SECTION\.KEY=VALUE"):
        load_settings(MODELS, None, ["budget"])


def test_bad_value_names_source_key_and_expectation(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as err:
        load_settings(MODELS, None, ["toy.budget=-3"])
    assert str(err.value).startswith("--set: toy.budget: Input should be greater than or equal to 0")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("toy:\n  budget: many\n")
    with pytest.raises(ConfigError, match=rf"{cfg}: toy.budget: Input should be a valid integer.*'many'"):
        load_settings(MODELS, cfg)


def test_malformed_and_missing_files(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("toy: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_settings(MODELS, bad)
    with pytest.raises(ConfigError, match="not found"):
        load_settings(MODELS, tmp_path / "missing.yaml")
    flat = tmp_path / "flat.yaml"
    flat.write_text("- a\n")
    with pytest.raises(ConfigError, match="expected a mapping of sections"):
        load_settings(MODELS, flat)


def test_default_yaml_is_in_sync_with_the_models() -> None:
    """configs/default.yaml is generated from the models; regenerate with `focusmap show-config --defaults`."""
    committed = (Path(__file__).resolve().parents[2] / "configs" / "default.yaml").read_text()
    assert committed == defaults_yaml(REGISTRY.models()), (
        "configs/default.yaml is stale: focusmap show-config --defaults > configs/default.yaml"
    )


def test_default_yaml_loads_back_and_documents_every_key(tmp_path: Path) -> None:
    text = defaults_yaml(REGISTRY.models())
    path = tmp_path / "d.yaml"
    path.write_text(text)
    settings = load_settings(REGISTRY.models(), path)
    for name, model in REGISTRY.models().items():
        assert settings[name] == model()
        for key, info in model.model_fields.items():
            assert info.description, f"{name}.{key} has no description"
            assert f"  # {info.description}" in text


def test_yaml_words_off_and_on_reach_choice_fields_as_words(tmp_path: Path) -> None:
    """YAML 1.1 reads an unquoted off / no as False: a choice field that offers the word gets the word back, from
    --set and from a file alike; a field that is a bool (or a bool or a word) keeps the bool."""
    s = load_settings(REGISTRY.models(), None, ["graph.noise_estimate=off", "graph.odometry_calibration=off"])
    assert s["graph"].noise_estimate == "off"
    assert s["graph"].odometry_calibration is False
    cfg = tmp_path / "c.yaml"
    cfg.write_text("graph:\n  noise_estimate: off\n  strict: yes\n")
    s = load_settings(REGISTRY.models(), cfg)
    assert s["graph"].noise_estimate == "off" and s["graph"].strict is True
    with pytest.raises(ConfigError, match="noise_estimate"):  # 'on' is not one of its choices
        load_settings(REGISTRY.models(), None, ["graph.noise_estimate=on"])
