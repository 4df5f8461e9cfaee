"""The GPU suite (benchmarks/gpu_suite.py) in its small mode on the CPU: every section runs and
reports, so the suite prepared for a GPU window cannot rot; and the packages it needs there
(benchmarks/gpu_carry.py) arrive whole."""

import json
import os
import shutil
import subprocess
import sys
import zipfile

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from benchmarks import gpu_carry, gpu_suite  # noqa: E402


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
            "--results",
            str(tmp_path / "returned"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    results = json.loads((tmp_path / "results.json").read_text())
    # what a lent machine's $OUT gets back (--results): the same figures
    assert json.loads((tmp_path / "returned" / "results.json").read_text())["sections"] == results["sections"]
    sections = results["sections"]
    assert set(sections) == {"throughput", "profile", "repeat", "agreement", "batched", "paper", "rover", "tests"}
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
    # the profile: every bed stepped; on the CPU the wall only (Warp's timing covers CUDA activity)
    profile = sections["profile"]["rows"]
    assert [(r["bed"], r["precision"]) for r in profile] == list(gpu_suite.PROFILE_ROWS)
    assert all(r["wall_us_per_step"] > 0 and r["kernel_us_per_step"] is None for r in profile)
    assert gpu_suite.kernel_name("forward kernel soil__solver__contact_kernels__locals__wrench_total_0a1b2c3d") == (
        "wrench_total"
    )
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
    assert all(title in text for title in ("| target | met |", "Profile", "Paper case", "Rover", "Batched replicas"))


def _wheel(folder, name, version, files):
    """A minimal wheel of `files` (path -> bytes), as pip installs it."""
    info = f"{name}-{version}.dist-info"
    files = {
        **files,
        f"{info}/METADATA": f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n".encode(),
        f"{info}/WHEEL": b"Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
    }
    files[f"{info}/RECORD"] = "".join(f"{path},,\n" for path in [*files, f"{info}/RECORD"]).encode()
    path = os.path.join(folder, f"{name}-{version}-py3-none-any.whl")
    with zipfile.ZipFile(path, "w") as wheel:
        for member, data in files.items():
            wheel.writestr(member, data)
    return path


def test_the_packages_carried_to_a_gpu_machine_arrive_whole(tmp_path):
    """benchmarks/gpu_carry.py: Warp's wheel and the suite's compiled kernels cut into parts that each fit
    a call, put back together into the very bytes they were; kernels packed from other sources than the
    tree's are named stale; a missing or damaged part is named, with the call that brings it."""
    rng = np.random.default_rng(0)
    native = {path: rng.integers(0, 4, 300_000, dtype=np.uint8).tobytes() for path in gpu_carry.NATIVE}
    wheels = [
        _wheel(tmp_path, "warp_lang", "1.0", {**native, "warp/__init__.py": b"ok = True\n"}),
        _wheel(tmp_path, "tomli_w", "1.0", {"tomli_w/__init__.py": b"ok = True\n"}),
    ]
    # a kernel cache as Warp writes it: per module its CPU object, its cubin for sm_90 and its metadata
    cache = tmp_path / "cache" / "1.0"
    for module in ("wp_soil_a_1234567", "wp_soil_b_89abcde"):
        (cache / module).mkdir(parents=True)
        for suffix in (".o", ".sm90.cubin", ".sm80.cubin", ".meta"):
            (cache / module / (module + suffix)).write_bytes(module.encode() + suffix.encode())
    carry, site, kernels = str(tmp_path / "carry"), str(tmp_path / "site"), str(tmp_path / "kernels")
    version = f"{sys.version_info[0]}.{sys.version_info[1]}"
    tree = tmp_path / "tree"  # the kernels' sources they were compiled from
    (tree / "soil" / "scm").mkdir(parents=True)
    (tree / "soil" / "solver.py").write_text("kernel = 1\n")
    (tree / "soil" / "scm" / "kernels.py").write_text("kernel = 2\n")
    manifest = gpu_carry.pack(
        version,
        carry,
        wheels=wheels,
        limit=100_000,
        kernels=str(tmp_path / "cache"),
        kernel_sources=gpu_carry.sources_digest(str(tree)),
    )
    assert len(manifest["parts"]) >= 2 and all(p["bytes"] <= 100_000 for p in manifest["parts"])
    assert gpu_carry.stale_kernels(gpu_carry.check(carry), str(tree)) is None
    (tree / "soil" / "scm" / "kernels.py").write_text("kernel = 3\n")  # a kernel changed after the pack
    assert "pack again" in gpu_carry.stale_kernels(gpu_carry.check(carry), str(tree))
    unsaid = {k: v for k, v in manifest.items() if k != "kernel_sources"}  # a pack from before the digest
    assert "pack again" in gpu_carry.stale_kernels(unsaid, str(tree))
    installed = gpu_carry.install(carry, site, kernels)
    assert installed[-1].startswith("2 Warp modules for sm_90")
    # only what an sm_90 device loads travels, at the path Warp's cache looks for it
    arrived = sorted(str(p.relative_to(kernels)) for p in (tmp_path / "kernels").rglob("*") if p.is_file())
    assert arrived == [
        f"1.0/{m}/{m}{s}" for m in ("wp_soil_a_1234567", "wp_soil_b_89abcde") for s in (".meta", ".sm90.cubin")
    ]
    assert (tmp_path / "kernels" / "1.0" / "wp_soil_a_1234567" / "wp_soil_a_1234567.sm90.cubin").read_bytes() == (
        b"wp_soil_a_1234567.sm90.cubin"
    )
    for path, data in native.items():
        assert (tmp_path / "site" / path).read_bytes() == data
    assert (tmp_path / "site" / "warp" / "__init__.py").read_bytes() == b"ok = True\n"
    assert (tmp_path / "site" / "tomli_w" / "__init__.py").is_file()
    assert any(p.name.startswith("warp_lang-1.0.dist-info") for p in (tmp_path / "site").iterdir())

    last = tmp_path / "carry" / str(len(manifest["parts"])) / "carry.tar.part"
    damaged = bytearray(last.read_bytes())
    damaged[0] ^= 0xFF
    last.write_bytes(bytes(damaged))
    with pytest.raises(gpu_carry.CarryError, match=f"part {len(manifest['parts'])} .* is damaged"):
        gpu_carry.check(carry)
    shutil.rmtree(tmp_path / "carry" / "1")
    with pytest.raises(gpu_carry.CarryError, match=r"part 1 is missing .*carry \['.gpu_carry/1'\]"):
        gpu_carry.install(carry, site)


KERNEL_SCRIPT = """
import os, sys
sys.path.insert(0, sys.argv[1])
import warp as wp
from benchmarks.gpu_suite import compile_loaded_modules

wp.config.log_level = wp.LOG_WARNING


@wp.kernel
def twice(a: wp.array(dtype=float)):
    a[wp.tid()] = 2.0 * a[wp.tid()]


values = wp.ones(4, dtype=float, device="cpu")
wp.launch(twice, dim=4, inputs=[values], device="cpu")
assert values.numpy().tolist() == [2.0] * 4
names = compile_loaded_modules(90)
module = twice.module
identifier = module.get_module_identifier(module.options["block_dim"])
print(module.name in names, os.path.join(wp.config.kernel_cache_dir, identifier, identifier + ".sm90.cubin"))
"""


def test_the_suites_kernels_compile_for_a_gpu_here(tmp_path):
    """gpu_suite --compile-for-arch: a module launched on this CPU is compiled for sm_90 without a GPU,
    to the path of Warp's kernel cache that a CUDA device of that architecture loads it from."""
    script = tmp_path / "compile.py"
    script.write_text(KERNEL_SCRIPT)
    done = subprocess.run(
        [sys.executable, str(script), ROOT],
        env={**os.environ, "WARP_CACHE_PATH": str(tmp_path / "cache")},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    listed, cubin = done.stdout.strip().splitlines()[-1].split(" ", 1)
    assert listed == "True"
    assert os.path.getsize(cubin) > 0 and cubin.startswith(str(tmp_path / "cache"))
    with open(cubin, "rb") as f:
        assert f.read(4) == b"\x7fELF"  # CUDA machine code is an ELF image


def test_occupancy_follows_cudas_rules():
    """benchmarks/kernel_resources.resident_warps against CUDA's occupancy rules for compute capability 9.0
    (65,536 registers per SM allocated per warp in units of 256, 64 warps, 32 blocks, 228 KiB of shared
    memory less 1 KiB per block), worked by hand."""
    from benchmarks.kernel_resources import resident_warps

    assert resident_warps(32) == 64  # 8 blocks of 8 warps: the warp limit
    assert resident_warps(64) == 32  # 64 x 32 x 8 = 16,384 registers a block: 4 blocks
    assert resident_warps(76) == 24  # 80 a thread once allocated: 20,480 a block, 3 blocks
    assert resident_warps(168) == 8 and resident_warps(255) == 8  # one block of 256 threads
    assert resident_warps(168, block_dim=128) == 12  # 21,504 registers a block: 3 blocks of 4 warps
    assert resident_warps(255, block_dim=128) == 8  # 32,768 a block: 2 blocks
    assert resident_warps(32, shared=48 * 1024) == 32  # 233,472 // 50,176 = 4 blocks
    assert resident_warps(16, block_dim=32) == 32  # 32 blocks of one warp: the block limit


REGISTER_SCRIPT = """
import sys
sys.path.insert(0, sys.argv[1])
import warp as wp
wp.config.quiet = True
from benchmarks.kernel_resources import cubin_kernels

def hungry(x: wp.array(dtype=wp.float64), y: wp.array(dtype=wp.float64)):
    i = wp.tid()
    a = wp.mat44d(x[i], x[i + 1], x[i + 2], x[i + 3], x[i + 4], x[i + 5], x[i + 6], x[i + 7],
                  x[i + 8], x[i + 9], x[i + 10], x[i + 11], x[i + 12], x[i + 13], x[i + 14], x[i + 15])
    b = wp.inverse(a) * a * wp.inverse(wp.transpose(a))
    y[i] = wp.determinant(b) + wp.trace(a * b)

for name, options in (("free", {}), ("capped", {"cuda_max_registers": 32})):
    kernel = wp.kernel(hungry, module=f"register_check_{name}", enable_backward=False, **options)
    (path,) = wp.compile_aot_module(kernel.module, arch=90, module_dir=sys.argv[2] + "/" + name, use_ptx=False)
    (figures,) = cubin_kernels(str(path)).values()
    print(name, figures["registers"], figures["stack_bytes"])
"""


def test_the_registers_read_from_a_cubin_are_the_compilers(tmp_path):
    """benchmarks/kernel_resources.cubin_kernels reads what NVRTC recorded for sm_90 (no GPU): a kernel held
    to 32 registers per thread (CUDA's __maxnreg__) reads at most 32 and spills to a stack, the same kernel
    free reads more than 32 and no stack."""
    script = tmp_path / "registers.py"
    script.write_text(REGISTER_SCRIPT)
    done = subprocess.run(
        [sys.executable, str(script), ROOT, str(tmp_path)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    read = {line.split()[0]: tuple(map(int, line.split()[1:])) for line in done.stdout.splitlines()[-2:]}
    assert read["capped"][0] <= 32 and read["capped"][1] > 0, read
    assert read["free"][0] > 32 and read["free"][1] == 0, read


def test_every_step_kernel_launches_at_its_modules_block_size(monkeypatch):
    """Warp compiles a module once per block size, and on a GPU a launch without one takes 256. A kernel
    launched at another block size than its module's option would run a copy that neither the preload
    before a graph's capture (soil.macro.StepGraphs.load_modules) nor the kernels compiled ahead for a
    lent GPU (gpu_suite --compile-for-arch) built. Every launch of a macro step and of the elastic energy
    (the contact module at soil.solver.CONTACT_BLOCK_DIM) passes its module's block size."""
    import warp as wp

    from soil import Simulation
    from soil.bed import BedSpec, build_bed

    launched = []
    launch = wp.launch

    def recorded(kernel, *args, **kwargs):
        block = kwargs.get("block_dim") or 256  # wp.launch's own default on a GPU
        launched.append((kernel.key, kernel.module.name, block, kernel.module.options["block_dim"]))
        return launch(kernel, *args, **kwargs)

    monkeypatch.setattr(wp, "launch", recorded)
    spec = BedSpec(length=0.04, width=0.03, depth=0.02, radius_mean=0.002)
    model, state, control = build_bed(spec, "moon").finalize(device="cpu", precision="mixed")
    simulation = Simulation(model, state, control)
    simulation.graphs.enabled = False  # every step's launches seen, not a replay
    simulation.macro_step(3, 1e-5)
    simulation.elastic_energy()
    contact = {module for _, module, _, option in launched if option != 256}
    assert any(key.endswith("grain_contacts") for key, *_ in launched) and contact, launched
    wrong = [(key, block, option) for key, _, block, option in launched if block != option]
    assert not wrong, wrong


def test_a_stop_ends_the_suite_with_the_sections_so_far_written(tmp_path, monkeypatch):
    """Ctrl-C or SIGTERM in a section (a run's RunInterrupted, or a stop its batch received) ends the
    suite with exit 130: the sections before it and the stopped one are in results.json, none after it
    runs (a lent machine's time is not spent on sections nobody waits for)."""
    from cosim.runner import RunInterrupted

    ran = []

    def fine(self):
        ran.append("throughput")
        return {"ok": True}

    def stopped(self):
        ran.append("profile")
        raise RunInterrupted("SIGTERM: stopped after its checkpoint", "SIGTERM")

    def never(self):
        ran.append("repeat")
        return {"ok": True}

    monkeypatch.setattr(gpu_suite.Suite, "throughput", fine)
    monkeypatch.setattr(gpu_suite.Suite, "profile", stopped)
    monkeypatch.setattr(gpu_suite.Suite, "repeat", never)
    argv = ["--small", "--device", "cpu", "--out", str(tmp_path), "--sections", "throughput", "profile", "repeat"]
    assert gpu_suite.main(argv) == 143  # SIGTERM's, as cosim's commands exit
    assert ran == ["throughput", "profile"]
    sections = json.loads((tmp_path / "results.json").read_text())["sections"]
    assert list(sections) == ["throughput", "profile"]
    assert sections["throughput"]["ok"] and not sections["profile"]["ok"]
    assert "SIGTERM" in sections["profile"]["error"]


def test_a_lammps_cpu_time_too_small_to_measure_is_nan_not_negative(monkeypatch):
    """benchmarks/throughput.py takes LAMMPS's CPU time as the difference of two runs (steps, 2 x steps):
    at a few steps the setups' scatter exceeds it and the table showed a negative CPU time per step."""
    from benchmarks import throughput

    clock = iter([0.0, 1.0, 1.0, 1.9])  # the longer run's setup happened to be faster: -0.1 s "per steps"
    monkeypatch.setattr(throughput.time, "process_time", lambda: next(clock))
    monkeypatch.setattr(throughput.lammps_peer, "run_bed", lambda *args, **kw: {"seconds": 0.5})
    row = throughput.time_lammps(np.zeros((4, 3)), np.full(4, 1e-3), (1, 1, 1), 1e-5, 10)
    assert np.isnan(row["cpu_seconds"]) and np.isnan(row["us_per_particle_step_cpu"])
    assert row["particle_steps_per_second"] == pytest.approx(4 * 10 / 0.5)
