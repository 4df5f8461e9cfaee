"""Linear stability of fixed-step jolt-Beeman on a damped oscillator a = -w^2 x - gamma v.

The forces of a step see the PREDICTED state (x+, v_pred = v + (3 a - a_minus) dt/2), so a
velocity-dependent force (contact damping) is extrapolated with the jolt. This prints,
from the spectral radius of the one-step map, the largest stable w dt for a few values
of gamma dt, and the largest stable gamma dt of pure damping.

Why it matters: a Kelvin tangential element with Lehr damping c_t = 2 D sqrt(m* k_t)
acts on the tangential mode whose inverse mass includes both grains' rotation,
1/m1 + 1/m2 + r1^2/I1 + r2^2/I2 = 3.5/m* for solid spheres, so that mode has
gamma_t = 7 D sqrt(k_t/m*). See BENCHMARKS.md (settling 20k grains).

    python benchmarks/jolt_beeman_damped_stability.py
"""

import numpy as np


def spectral_radius(w_dt: float, gamma_dt: float) -> float:
    """Largest |eigenvalue| of one jolt-Beeman step on (x, v dt, a dt^2, a_minus dt^2)."""
    columns = []
    for unit in np.eye(4):
        x, v, a, a_minus = unit
        x_new = x + v + (4 * a - a_minus) / 6
        v_pred = v + (3 * a - a_minus) / 2
        a_new = -(w_dt**2) * x_new - gamma_dt * v_pred
        v_new = v + (2 * a_new + 5 * a - a_minus) / 6
        columns.append([x_new, v_new, a_new, a])
    return float(max(abs(np.linalg.eigvals(np.array(columns).T))))


def largest_stable(values, radius_of) -> float:
    """The last value of an increasing grid before the spectral radius exceeds 1."""
    stable = 0.0
    for value in values:
        if radius_of(value) > 1 + 1e-9:
            break
        stable = value
    return stable


if __name__ == "__main__":
    grid = np.linspace(1e-3, 3.0, 3000)
    print("| gamma dt | largest stable w dt |\n|---|---|")
    for gamma_dt in (0.0, 0.1, 0.2, 0.3, 0.4, 0.5):
        stable = largest_stable(grid, lambda w, gamma_dt=gamma_dt: spectral_radius(w, gamma_dt))
        print(f"| {gamma_dt:.1f} | {stable:.3f} |")
    print(
        f"\npure damping (w = 0): stable for gamma dt <= {largest_stable(grid, lambda g: spectral_radius(0.0, g)):.3f}"
    )
