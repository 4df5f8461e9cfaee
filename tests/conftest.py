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


@pytest.fixture(scope="session")
def tiny_bed(tmp_path_factory):
    """The tiny scene's settled bed (tests/helpers.py TINY_SCENE), settled once per session."""
    from cosim.beds import settled_bed
    from cosim.plan import load_plan
    from helpers import write_tiny

    folder = tmp_path_factory.mktemp("tiny_bed")
    return settled_bed(load_plan(write_tiny(folder)), str(folder)).path


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory, tiny_bed):
    """A run folder of the tiny scene on its settled bed, made once per session (read it, do not change it)."""
    from cosim.launch import run_scene
    from helpers import write_tiny

    folder = tmp_path_factory.mktemp("tiny_run")
    result = run_scene(write_tiny(folder), str(folder / "run"), overrides=[f'bed.bed_file="{tiny_bed}"'])
    assert result.status in ("complete", "unsteady")
    return folder / "run"
