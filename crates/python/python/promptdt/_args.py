"""Argument checks shared by the package's modules, without gymnasium (``promptdt.envs`` needs it;
``train``, ``evaluate`` and ``collect`` do not)."""
from __future__ import annotations

from typing import Any, Optional

import numpy as np
from .errors import ArgumentTypeError, InvalidInputError


def _uint(name: str, value: Any, expected: str, *, low: int = 0, high: Optional[int] = None) -> int:
    """An integer argument in ``[low, high)``, or a ``TypeError``/``ValueError`` that names it, what
    was given and what is expected."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ArgumentTypeError(f"{name}: {value!r} ({type(value).__name__}) given, expected {expected} (an int)")
    v = int(value)
    if v < low or (high is not None and v >= high):
        rng = f">= {low}" if high is None else f"in [{low}, {high})"
        raise InvalidInputError(f"{name}: {v} given, expected {expected} ({rng})")
    return v
