"""The types of JSON data: what ``json.loads`` returns and what the run folder's JSON files hold."""

from __future__ import annotations

from typing import TypeAlias

JSONValue: TypeAlias = "str | int | float | bool | list[JSONValue] | dict[str, JSONValue] | None"
"""A value JSON can hold."""

JSONObject: TypeAlias = dict[str, JSONValue]
"""A JSON object (a mapping with string keys)."""
