"""How much memory a soil of N grains takes, before it is allocated, and whether this machine has it.

The device bytes per grain are those of `Simulation.bytes_per_grain()` (state buffers, layout,
contact and list scratch, the divergence monitor's last good state), measured once per
precision on an 11,368-grain bed (mixed; 25,440 for single and double) with rolling friction
on (its largest layout) at two contact capacities (docs/performance.md section 5), plus the
contact kernels' torque sums (12 B single, 24 B mixed and double) added since, and the grains'
constants and the control's external force, which that measure left out (32 B single, 44 B mixed,
60 B double: four reals and a material index in the storage type, a 3-vector in the accumulation
type), and the neighbour list saved at each macro step's start, left out too (4 B a slot, and a
count and a build position: 16 B single, 28 B mixed and double). They are
linear in the contact slots per grain (mixed keeps its contact history in float32, as single
does):

    device bytes per grain = BASE[precision] + PER_SLOT[precision] x contact_capacity

(the 4 wall/wheel slots are in BASE). The host needs HOST_BYTES_PER_GRAIN more while the grains
are inserted and the model is built (numpy arrays, measured with tracemalloc); on the CPU device
the device arrays are host memory too. A neighbour list that overflows grows its capacity, so
the estimate is the start of a run, not its worst case.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from .errors import InputError

BASE_BYTES = {"single": 1092 + 32 + 16, "mixed": 1440 + 44 + 28, "double": 2001 + 60 + 28}
"""Device bytes per grain besides the pair contact slots (4 wall/wheel slots included) [B]."""
PER_SLOT_BYTES = {"single": 112 + 4, "mixed": 112 + 4, "double": 208 + 4}
"""Device bytes per pair contact slot of a grain (three state buffers, the monitor's copy, the saved list) [B]."""
HOST_BYTES_PER_GRAIN = 400
"""Host bytes per grain while a bed is inserted and its model built (measured peak about 370 B) [B]."""
DEFAULT_CONTACT_CAPACITY = 16
"""Pair contact slots per grain at the start (SoilBuilder.finalize's default)."""


class SoilTooLargeError(InputError, ValueError):
    """The soil does not fit this machine's free memory: the message gives the estimate and what is free."""


def device_bytes_per_grain(precision: str, contact_capacity: int = DEFAULT_CONTACT_CAPACITY) -> int:
    """Device bytes per grain of a Simulation in `precision` (the module docstring's formula) [B]."""
    return BASE_BYTES[precision] + PER_SLOT_BYTES[precision] * int(contact_capacity)


@dataclass(frozen=True)
class MemoryEstimate:
    grains: int
    precision: str
    device: str
    device_bytes: int
    """On the Warp device (host memory when the device is the CPU) [B]."""
    host_bytes: int
    """On the host besides the device arrays (the CPU device: both together) [B]."""
    device_free: int | None
    """Free memory of a CUDA device as Warp reports it [B] (None: the CPU, or not reported)."""
    host_free: int | None
    """Available host memory [B] (None: not reported)."""

    @property
    def fits(self) -> bool:
        host_ok = self.host_free is None or self.host_bytes <= self.host_free
        device_ok = self.device_free is None or self.device_bytes <= self.device_free
        return host_ok and device_ok

    def text(self) -> str:
        size = format_bytes
        if self.device.startswith("cuda"):
            return (
                f"{self.grains:,} grains in {self.precision}: about {size(self.device_bytes)} on {self.device} "
                f"({size(self.device_free)} free) and {size(self.host_bytes)} of host memory "
                f"({size(self.host_free)} free)"
            )
        return (
            f"{self.grains:,} grains in {self.precision}: about {size(self.host_bytes)} of host memory "
            f"({size(self.host_free)} free)"
        )


def format_bytes(value: int | None) -> str:
    """A byte count as GB or MB, for messages ("unknown" for None)."""
    if value is None:
        return "unknown"
    return f"{value / 1e9:.3g} GB" if value >= 1e9 else f"{value / 1e6:.3g} MB"


def free_host_memory() -> int | None:
    """Available host memory [B]: /proc/meminfo's MemAvailable, else the free pages (None when neither)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def free_device_memory(device: str) -> int | None:
    """Free memory of a CUDA device as Warp reports it [B]; None for the CPU or when unknown."""
    import warp as wp

    try:
        found = wp.get_device(device)
        if not found.is_cuda:
            return None
        return int(found.free_memory)
    except Exception:  # an unknown device is reported elsewhere (scene.device); here it is just unknown
        return None


def estimate(
    grains: int, precision: str, device: str, contact_capacity: int = DEFAULT_CONTACT_CAPACITY
) -> MemoryEstimate:
    """The memory a soil of `grains` grains needs on `device` (module docstring) and what is free."""
    on_device = int(grains) * device_bytes_per_grain(precision, contact_capacity)
    host = int(grains) * HOST_BYTES_PER_GRAIN
    cuda = str(device).startswith("cuda")
    return MemoryEstimate(
        int(grains),
        precision,
        str(device),
        on_device,
        host if cuda else host + on_device,
        free_device_memory(device) if cuda else None,
        free_host_memory(),
    )


BED_KEYS = "bed.length, bed.width, bed.depth, bed.radius_mean"


def check_fits(found: MemoryEstimate, what: str, keys: str = BED_KEYS) -> None:
    """SoilTooLargeError with the estimate and the free memory when `found` does not fit; `keys` are the
    scene keys that size the soil."""
    if not found.fits:
        raise SoilTooLargeError(
            f"{what} does not fit this machine: {found.text()}; make the soil smaller or the grains larger "
            f"({keys}), or use a machine with more memory"
        )
