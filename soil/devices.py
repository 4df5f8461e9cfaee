"""Which Warp device a soil runs on: a name checked against this machine before Warp is asked (Warp's
own errors name no allowed value, and asking a machine without CUDA for 'cuda' prints driver errors)."""

from __future__ import annotations

from .errors import SoilInputError


def device_names() -> list[str]:
    """The devices this machine has: 'cpu' and 'cuda:N' for each CUDA device Warp sees."""
    import warp as wp

    count = wp.get_cuda_device_count() if wp.is_cuda_available() else 0
    return ["cpu"] + [f"cuda:{i}" for i in range(count)]


def warp_device(device=None) -> str:
    """The Warp device name of `device`: 'cpu', 'cuda' (the current CUDA device), 'cuda:N', a Warp Device,
    or None (Warp's default); SoilInputError naming the devices this machine has when it has no such one."""
    import warp as wp

    if device is None or isinstance(device, wp.Device):
        return str(wp.get_device(device))
    have = device_names()
    if device in have or (device == "cuda" and len(have) > 1):
        return str(wp.get_device(device))
    raise SoilInputError(f"device {device!r}: this machine has {', '.join(have)} (or None: Warp's default)")
