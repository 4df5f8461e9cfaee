"""Shared test setup: every soil test runs once per available Warp device (CPU always)."""

import os

import pytest
import warp as wp

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
os.environ.setdefault("MPLBACKEND", "Agg")


def _devices():
    wp.init()
    devices = ["cpu"]
    if wp.is_cuda_available():
        devices.append("cuda:0")
    return devices


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request):
    """Each test that takes `device` runs on the CPU and, when present, on CUDA."""
    return request.param
