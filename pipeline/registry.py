"""The stage registry: the pipeline's stages in order."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from pydantic import BaseModel

from pipeline.errors import ConfigError
from pipeline.stage import Stage


class Registry:
    """Stages by name, in pipeline order."""

    def __init__(self, stages: Iterable[Stage]) -> None:
        self._stages = {s.name: s for s in stages}
        for s in self._stages.values():
            for dep in (*s.inputs, *s.optional_inputs):
                if dep not in self._stages:
                    raise ValueError(f"stage {s.name!r} reads unknown stage {dep!r}")

    def __iter__(self) -> Iterator[Stage]:
        return iter(self._stages.values())

    def __contains__(self, name: object) -> bool:
        return name in self._stages

    def __getitem__(self, name: str) -> Stage:
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

    def between(self, start: str | None = None, until: str | None = None) -> list[Stage]:
        """The stages from ``start`` to ``until`` inclusive, in order."""
        names = self.names
        i = names.index(self[start].name) if start else 0
        j = names.index(self[until].name) if until else len(names) - 1
        if j < i:
            raise ConfigError(f"--until {until!r} comes before --from {start!r}")
        return [self._stages[n] for n in names[i : j + 1]]
