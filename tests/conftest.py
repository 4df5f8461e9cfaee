"""Shared test setup: every soil test runs once per available Warp device (CPU always)."""

import os
from pathlib import Path

import pytest
import warp as wp

from soil import quiet_warp

os.environ.setdefault("MPLBACKEND", "Agg")


def _devices():
    quiet_warp()  # no per-module load lines, no CUDA-driver warning on a machine without a GPU
    devices = ["cpu"]
    if wp.is_cuda_available():
        devices.append("cuda:0")
    return devices


DEVICES = _devices()


def cpu_quota_cores(cgroup: Path = Path("/sys/fs/cgroup")) -> int | None:
    """The cores a container's CPU quota allows, rounded up (cgroup v2 `cpu.max`, else v1
    `cpu/cpu.cfs_quota_us` over `cpu.cfs_period_us`); None without a quota."""
    try:
        quota, period = (cgroup / "cpu.max").read_text().split()[:2]
    except (OSError, ValueError):
        try:
            v1 = cgroup / "cpu"
            quota, period = ((v1 / name).read_text().strip() for name in ("cpu.cfs_quota_us", "cpu.cfs_period_us"))
        except OSError:
            return None
    if quota in ("max", "-1"):
        return None
    return max(1, -(-int(quota) // int(period)))


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist: pytest without it (the lent GPU machine) runs too
def pytest_xdist_auto_num_workers(config):
    """`-n auto` (pyproject's default): one worker per core this process may use, counting a
    container's CPU quota, which os.cpu_count() ignores."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return min(cores, cpu_quota_cores() or cores)


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
