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
    assert set(sections) == {"throughput", "repeat", "agreement", "batched", "paper", "rover", "tests"}
    assert all(section["ok"] for section in sections.values()), sections
    assert sections["repeat"]["bitwise_equal"] and sections["repeat"]["wheel_contacts_max"] > 0
    rows = sections["throughput"]["rows"]
    assert {(r["bed"], r["precision"]) for r in rows} == {
        (b, p) for b in ("100k", "1M") for p in ("single", "mixed", "double")
    }
    assert all(r["particle_steps_per_second"] > 0 and r["captured"] for r in rows)
    assert all(r["bytes_per_grain"] > 0 and r["bytes_per_grain_estimate"] > 0 for r in rows)
    slot = sections["throughput"]["slot_rows"]  # the slot-major storage measured beside the per-grain one
    assert {(r["bed"], r["precision"]) for r in slot} == {(b, p) for b in ("100k", "1M") for p in ("single", "mixed")}
    assert all(r["x_grain_storage"] > 0 for r in slot)
    layout = sections["throughput"]["layout"]
    assert layout["double"]["x_double"] == 1.0 and 0 < layout["mixed"]["x_double"] < 1
    # the paper case drives with its wheel in the grains: it touches them at every macro step
    paper = sections["paper"]
    assert paper["drive_steps"] > 0 and paper["wheel_contacts"]["drive_min"] > 0
    assert paper["projected_60s_seconds"] > 0 and paper["particle_steps_per_second"] > 0
    rover = sections["rover"]
    assert rover["drive_steps"] > 0 and rover["particle_steps_per_second"] > 0 and rover["grains_min"] > 0
    batched = sections["batched"]  # replicas as worlds of one simulation: world 0 is its run alone
    assert batched["world_0_as_alone"] and [r["worlds"] for r in batched["rows"]] == ["alone", 1, 2]
    assert all(r["particle_steps_per_second"] > 0 and r["wheel_contacts_min"] > 0 for r in batched["rows"])
    assert all(r["host_ms_per_world_step"] > 0 and 0 < r["dem_share_of_wall"] < 1 for r in batched["rows"][1:])
    assert all(0 < r["serve_ms_per_world_step"] < 1e3 for r in batched["rows"][1:])
    text = (tmp_path / "results.md").read_text()
    assert "| target | met |" in text and "Paper case" in text and "Rover" in text and "Batched replicas" in text
