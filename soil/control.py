"""Control: what the user prescribes from outside the soil."""

from __future__ import annotations

import warp as wp


class SoilControl:
    """External inputs of a step."""

    def __init__(self, particle_count: int, vec_hi, device: str):
        self.external_force = wp.zeros(particle_count, dtype=vec_hi, device=device)
        """Extra force on each particle [N], shape (particle_count,); zero by default."""
