"""Field helpers shared by the bulk-data converters: blank numbers and component codes."""

from __future__ import annotations

import numpy as np


def field_float(value, default=np.nan) -> float:
    """A card field as float; ``default`` for a blank (None) field."""
    return default if value is None else float(value)


def component_mask(code) -> np.ndarray:
    """Nastran component code (``123456`` subset, int or str) as a (6,) bool mask.

    Blank, 0 and "0" give no components.

    Raises
    ------
    ValueError
        When a digit outside 1..6 appears (the caller names card and id).
    """
    mask = np.zeros(6, bool)
    if code in (None, "", 0, "0"):
        return mask
    for ch in str(int(code)) if not isinstance(code, str) else code.strip():
        if ch not in "123456":
            raise ValueError(f"bad component code {code!r}")
        mask[int(ch) - 1] = True
    return mask


def component_string(code) -> str:
    """Normalized component string ('123456' subset, sorted), '' for blank/0."""
    m = component_mask(code)
    return "".join(str(i + 1) for i in np.flatnonzero(m))
