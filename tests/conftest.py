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


def pytest_xdist_auto_num_workers(config):
    """`-n auto` (pyproject's default): one worker per core this process may use, counting a
    container's CPU quota (cgroup v2 cpu.max, v1 cfs_quota_us), which os.cpu_count() ignores."""
    from pathlib import Path

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    v1 = Path("/sys/fs/cgroup/cpu")
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
    except (OSError, ValueError):
        try:
            quota, period = ((v1 / name).read_text().strip() for name in ("cpu.cfs_quota_us", "cpu.cfs_period_us"))
        except OSError:
            quota, period = "max", "1"
    if quota not in ("max", "-1"):
        cores = min(cores, max(1, -(-int(quota) // int(period))))
    return cores


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
