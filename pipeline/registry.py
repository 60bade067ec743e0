"""The stage registry: the pipeline's stages in order."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Literal, TypeAlias

from pydantic import BaseModel

from pipeline.errors import ConfigError
from pipeline.stage import AnyStage

HeadlineType: TypeAlias = Literal["int64", "float64"]
"""Column types of headline figures (pyarrow type names)."""


@dataclass(frozen=True)
class Headline:
    """A figure of a run that batch tables show, read from the stages' ``summary.json``.

    Attributes:
        dtype: its column type, a pyarrow type name (``"int64"``, ``"float64"``; an integer column counts the
            items of a list it finds).
        places: ``(stage, key)`` places to look, first present wins; a dotted key reaches into nested
            summaries (``"headline.collision_rate"``). If none is present, the column's own name is looked
            up in every stage's summary, latest stage first.
        short: its column label in the printed table.
    """

    dtype: HeadlineType
    places: tuple[tuple[str, str], ...] = ()
    short: str = ""


class Registry:
    """Stages by name, in pipeline order, with the headline figures batch tables show and short labels."""

    def __init__(
        self,
        stages: Iterable[AnyStage],
        headlines: Mapping[str, Headline] | None = None,
        short_names: Mapping[str, str] | None = None,
    ) -> None:
        self._stages = {s.name: s for s in stages}
        for s in self._stages.values():
            for dep in (*s.inputs, *s.optional_inputs):
                if dep not in self._stages:
                    raise ValueError(f"stage {s.name!r} reads unknown stage {dep!r}")
        self.headlines: dict[str, Headline] = dict(headlines or {})
        for column, h in self.headlines.items():
            for stage, _ in h.places:
                if stage not in self._stages:
                    raise ValueError(f"headline {column!r} reads unknown stage {stage!r}")
        self.short_names: dict[str, str] = dict(short_names or {})

    def __iter__(self) -> Iterator[AnyStage]:
        return iter(self._stages.values())

    def __contains__(self, name: object) -> bool:
        return name in self._stages

    def __getitem__(self, name: str) -> AnyStage:
        key = name.replace("-", "_")
        if key not in self._stages:
            raise ConfigError(f"unknown stage {name!r}; stages: {', '.join(s.command for s in self)}")
        return self._stages[key]

    @property
    def names(self) -> list[str]:
        """Stage names in order."""
        return list(self._stages)

    def models(self) -> dict[str, type[BaseModel]]:
        """Settings model of every stage, by section name."""
        return {s.name: s.config_type for s in self}

    def between(self, start: str | None = None, until: str | None = None) -> list[AnyStage]:
        """The stages from ``start`` to ``until`` inclusive, in order."""
        names = self.names
        i = names.index(self[start].name) if start else 0
        j = names.index(self[until].name) if until else len(names) - 1
        if j < i:
            raise ConfigError(f"--until {until!r} comes before --from {start!r}")
        return [self._stages[n] for n in names[i : j + 1]]
