"""The test workers' count: a container's CPU quota, read as the kernel's cgroup files give it."""

import subprocess
import sys
from pathlib import Path

from conftest import cpu_quota_cores


def test_a_cgroup_v2_quota_rounds_up_to_whole_cores(tmp_path):
    (tmp_path / "cpu.max").write_text("150000 100000\n")  # 1.5 cores of CPU time per period
    assert cpu_quota_cores(tmp_path) == 2
    (tmp_path / "cpu.max").write_text("50000 100000\n")
    assert cpu_quota_cores(tmp_path) == 1
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert cpu_quota_cores(tmp_path) is None


def test_a_cgroup_v1_quota_and_no_quota(tmp_path):
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("200000\n")
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert cpu_quota_cores(tmp_path) == 2
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert cpu_quota_cores(tmp_path) is None
    assert cpu_quota_cores(tmp_path / "absent") is None


def test_the_suite_runs_under_a_pytest_without_xdist():
    """The lent GPU machine's pytest has no pytest-xdist (benchmarks/gpu_suite.py runs it with
    `-o addopts=`): the suite's conftest must load there, its xdist hook unused."""
    root = Path(__file__).resolve().parents[1]
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-o", "addopts=", "-p", "no:cacheprovider"]
    done = subprocess.run([*command, "tests/test_workers.py", "-k", "quota"], cwd=root, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "2 passed" in done.stdout
