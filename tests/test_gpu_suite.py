"""The GPU suite (benchmarks/gpu_suite.py) in its small mode on the CPU: every section runs and
reports, so the suite prepared for a GPU window cannot rot."""

import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_the_gpu_suite_runs_small_on_the_cpu(tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "benchmarks", "gpu_suite.py"),
            "--small",
            "--device",
            "cpu",
            "--out",
            str(tmp_path),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    results = json.loads((tmp_path / "results.json").read_text())
    sections = results["sections"]
    assert set(sections) == {"throughput", "repeat", "agreement", "paper", "tests"}
    assert all(section["ok"] for section in sections.values()), sections
    assert sections["repeat"]["bitwise_equal"] and sections["repeat"]["wheel_contacts_max"] > 0
    rows = sections["throughput"]["rows"]
    assert {(r["bed"], r["precision"]) for r in rows} == {
        (b, p) for b in ("100k", "1M") for p in ("single", "mixed", "double")
    }
    assert all(r["particle_steps_per_second"] > 0 and r["captured"] for r in rows)
    assert sections["paper"]["projected_60s_seconds"] > 0
    assert "| target | met |" in (tmp_path / "results.md").read_text()
