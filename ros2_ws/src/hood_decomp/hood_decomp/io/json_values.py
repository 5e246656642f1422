"""JSON has no NaN or infinity: the one rule that turns results into JSON-ready values (non-finite numbers -> null),
and the one reader that holds files to it (:func:`loads_strict`)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np


def json_ready(value: object) -> Any:
    """``value`` with every non-finite number (NaN, +-inf) replaced by None and numpy scalars and arrays turned into
    Python numbers and lists, through mappings, lists and tuples; ``json.dumps(..., allow_nan=False)`` accepts it."""
    if isinstance(value, Mapping):
        return {key: json_ready(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_ready(item) for item in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        number = float(value)
        return number if math.isfinite(number) else None
    return value


def loads_strict(text: str) -> Any:
    """``json.loads`` that refuses NaN, Infinity and -Infinity (Python's reader accepts them; JSON has none) and
    nesting deep enough to exhaust the stack; ValueError (with the reason) for both."""
    try:
        return json.loads(text, parse_constant=_no_constant)
    except RecursionError as error:
        raise ValueError("JSON nested too deeply") from error


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number")
