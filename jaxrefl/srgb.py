"""The sRGB transfer curve (IEC 61966-2-1), the one place jaxrefl converts.

Host-side NumPy; values of any shape, float64 out. `to_linear` decodes
photographs (ingest, the relight reference); `from_linear` and `from_linear8`
encode pictures and PLY vertex colours.
"""

from __future__ import annotations

import numpy as np

__all__ = ["to_linear", "from_linear", "from_linear8"]

#: Encoded values at or below this are linear (slope 1/12.92) ...
KNEE_ENCODED = 0.04045
#: ... and linear values at or below this (= KNEE_ENCODED / 12.92, to 7 digits).
KNEE_LINEAR = 0.0031308


def to_linear(x) -> np.ndarray:
    """sRGB-encoded values in [0, 1], any shape, to linear float64 (same shape)."""
    x = np.asarray(x, dtype=np.float64)
    curve = ((np.maximum(x, KNEE_ENCODED) + 0.055) / 1.055) ** 2.4
    return np.where(x <= KNEE_ENCODED, x / 12.92, curve)


def from_linear(x) -> np.ndarray:
    """Linear values, any shape, clipped to [0, 1], to sRGB-encoded float64 (same shape)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    curve = 1.055 * np.power(np.maximum(x, KNEE_LINEAR), 1 / 2.4) - 0.055
    return np.where(x <= KNEE_LINEAR, 12.92 * x, curve)


def from_linear8(x) -> np.ndarray:
    """Linear values, any shape, clipped to [0, 1], to sRGB uint8 codes (same shape)."""
    return np.round(from_linear(x) * 255).astype(np.uint8)
