"""Gravity presets [m/s^2]. A scene's gravity is a vector; these are magnitudes along -Z."""

from __future__ import annotations

import numpy as np

from .errors import SoilInputError

GRAVITY_PRESETS: dict[str, float] = {
    "earth": 9.80665,
    "mars": 3.721,
    "moon": 1.625,
    "phobos": 5.7e-3,  # nominal effective surface gravity (paper section 1.2)
    "phobos_min": 3.0e-3,  # lower extreme of the effective gravity on Phobos
    "phobos_max": 6.8e-3,  # upper extreme
    "deimos": 3.0e-3,
}
"""The magnitude of each named gravity [m/s^2] (a scene's `gravity = "phobos"`), along -Z."""


def gravity_vector(value) -> np.ndarray:
    """Gravity vector [m/s^2], shape (3,), from a preset name, a magnitude (along -Z) or a 3-vector."""
    if isinstance(value, str):
        if value not in GRAVITY_PRESETS:
            raise SoilInputError(f"gravity preset must be one of {sorted(GRAVITY_PRESETS)}, got {value!r}")
        return np.array([0.0, 0.0, -GRAVITY_PRESETS[value]])
    array = np.asarray(value, dtype=np.float64)
    if array.ndim == 0:
        if not np.isfinite(array) or array < 0:
            raise SoilInputError(f"gravity magnitude must be a finite number >= 0 [m/s^2], got {value!r}")
        return np.array([0.0, 0.0, -float(array)])
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise SoilInputError(f"gravity must be a preset name, a magnitude or 3 finite numbers [m/s^2], got {value!r}")
    return array.copy()
