"""JSON as the API accepts it: finite numbers only and a bounded nesting depth, refused naming the field.

Python's json module reads `NaN`, `Infinity` and `-Infinity` as floats and recurses once per nesting
level (RecursionError near 1000 levels); neither may reach a route. `loads(text, field)` checks the depth
with a flat scan first, then parses with the constants made visible, and raises `JsonRefused` whose
message names the offending element, e.g. `body.position[2]: NaN is not a finite number`.
"""

from __future__ import annotations

import json
import math
from typing import Any

MAX_JSON_DEPTH = 32
"""Deepest nesting of arrays and objects in any request: the API's documents go 4 levels deep."""


class JsonRefused(ValueError):
    """Text the API does not accept as JSON; its message names the field."""


class _NonFinite:
    """Stands for a NaN/Infinity literal while parsing, so its place can be named afterwards."""

    def __init__(self, literal: str) -> None:
        self.literal = literal


def _finite_or_placeholder(literal: str) -> float | _NonFinite:
    number = float(literal)  # 1e999 overflows to inf
    return number if math.isfinite(number) else _NonFinite(literal)


def nesting_depth(text: str) -> int:
    """The deepest nesting of [ and { outside strings, without recursion."""
    depth = deepest = 0
    in_string = escaped = False
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    return deepest


def _non_finite_path(value: Any, field: str) -> tuple[str, str] | None:
    """(path, literal) of the first NaN/Infinity placeholder in a parsed document, depth first."""
    pending: list[tuple[Any, str]] = [(value, field)]
    while pending:
        item, path = pending.pop()
        if isinstance(item, _NonFinite):
            return path, item.literal
        if isinstance(item, dict):
            pending.extend((child, f"{path}.{key}") for key, child in reversed(item.items()))
        elif isinstance(item, list):
            pending.extend((child, f"{path}[{index}]") for index, child in reversed(list(enumerate(item))))
    return None


def loads(text: str | bytes, field: str) -> Any:
    """The parsed document, or JsonRefused naming `field` (and the element inside it) with the reason."""
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError:
            raise JsonRefused(f"{field}: not UTF-8 text") from None
    if nesting_depth(text) > MAX_JSON_DEPTH:
        raise JsonRefused(f"{field}: nested deeper than {MAX_JSON_DEPTH} levels")
    try:
        value = json.loads(text, parse_constant=_NonFinite, parse_float=_finite_or_placeholder)
    except json.JSONDecodeError as error:
        raise JsonRefused(f"{field}: not valid JSON ({error})") from None
    found = _non_finite_path(value, field)
    if found is not None:
        path, literal = found
        raise JsonRefused(f"{path}: {literal} is not a finite number; JSON numbers must be finite")
    return value
