"""The registers and stack of the DEM step's CUDA kernels, and the occupancy they allow, read from the
machine code compiled here for a GPU architecture: no GPU needed.

    python benchmarks/kernel_resources.py                          # this checkout, sm_90 (H100, H200)
    python benchmarks/kernel_resources.py --compare /path/to/old   # another checkout beside this one
    python benchmarks/kernel_resources.py --compare /path/to/old --json   # both as [{checkout, rows}, ...]

Each kernel of a DEM step (the contact, integrator and neighbour modules of soil/, for each
precision, with and without rolling resistance) is compiled by Warp's NVRTC for the architecture
(`wp.compile_aot_module`: a cubin), and the compiler's own record of each kernel is read from it:
its registers per thread (the EIATTR_REGCOUNT attribute of the cubin's .nv.info section) and the
stack it needs (EIATTR_MIN_STACK_SIZE: spills and local arrays, in local memory). From the registers,
the block size Warp launches with (its module's: 256, the contact module's 128) and the static shared
memory, CUDA's occupancy rules (at block sizes that are multiples of 128) give
the warps one SM keeps resident, which is what hides the latency of the grains' neighbour gathers
in a memory-bound step. These are the compiler's figures, not a timing: what they change in
particle-steps/s only a GPU measures (benchmarks/gpu_suite.py).
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARCH = 90
BLOCK_DIM = 256
"""Threads per block of Warp's launches (a module's default block_dim), unless its module says otherwise."""
EIATTR_REGCOUNT = 0x2F
EIATTR_MIN_STACK_SIZE = 0x12
EIFMT_SVAL = 0x04
"""A record with a 2-byte size and that many bytes of value; the others (EIFMT_NVAL 0x01, EIFMT_BVAL
0x02, EIFMT_HVAL 0x03) take 4 bytes in all."""


class SM:
    """CUDA's per-SM limits for compute capability 9.0 (the CUDA C++ Programming Guide's table of
    technical specifications per compute capability)."""

    registers = 65536
    """32-bit registers per SM."""
    register_unit = 256
    """Registers are allocated per warp in units of this many."""
    warps = 64
    """Resident warps per SM at most."""
    blocks = 32
    """Resident blocks per SM at most."""
    shared = 233472
    """Shared memory per SM [B] (228 KiB)."""
    shared_reserved = 1024
    """Shared memory the system reserves per block [B]."""


def resident_warps(registers: int, shared: int = 0, block_dim: int = BLOCK_DIM) -> int:
    """Warps one SM keeps resident for a kernel of `registers` per thread and `shared` bytes of static
    shared memory per block, launched in blocks of `block_dim` threads (CUDA's occupancy rules)."""
    warps_per_block = -(-block_dim // 32)
    per_warp = -(-max(registers, 1) * 32 // SM.register_unit) * SM.register_unit
    by_registers = SM.registers // (per_warp * warps_per_block)
    by_warps = SM.warps // warps_per_block
    by_shared = SM.shared // (shared + SM.shared_reserved)
    return min(by_registers, by_warps, by_shared, SM.blocks) * warps_per_block


def _nv_info(data: bytes) -> dict[int, list[tuple[int, int]]]:
    """The (symbol, value) pairs of each per-function attribute in a cubin's .nv.info section."""
    import io

    from elftools.elf.elffile import ELFFile

    elf = ELFFile(io.BytesIO(data))
    section = elf.get_section_by_name(".nv.info")
    raw = section.data() if section is not None else b""
    attributes: dict[int, list[tuple[int, int]]] = {}
    p = 0
    while p + 2 <= len(raw):
        form, attribute = raw[p], raw[p + 1]
        if form == EIFMT_SVAL:
            (size,) = struct.unpack_from("<H", raw, p + 2)
            value = raw[p + 4 : p + 4 + size]
            p += 4 + size
            if size == 8:
                attributes.setdefault(attribute, []).append(struct.unpack("<II", value))
        else:
            p += 4
    return attributes


def cubin_kernels(path: str) -> dict[str, dict]:
    """Per kernel of a cubin (by its name): registers per thread, stack [B] and static shared memory [B]."""
    import io

    from elftools.elf.elffile import ELFFile

    with open(path, "rb") as f:
        data = f.read()
    elf = ELFFile(io.BytesIO(data))
    symbols = elf.get_section_by_name(".symtab")
    names = [symbol.name for symbol in symbols.iter_symbols()]
    info = _nv_info(data)
    stack = {names[s]: v for s, v in info.get(EIATTR_MIN_STACK_SIZE, [])}
    kernels = {}
    for s, registers in info.get(EIATTR_REGCOUNT, []):
        name = names[s]
        shared = elf.get_section_by_name(f".nv.shared.{name}")
        kernels[name] = {
            "registers": registers,
            "stack_bytes": stack.get(name, 0),
            "shared_bytes": shared["sh_size"] if shared is not None else 0,
        }
    return kernels


def _short(name: str) -> str:
    """A Warp kernel's name in its cubin, without the factory's prefix, the hash and the suffix."""
    name = name.removesuffix("_cuda_kernel_forward").split("__locals__")[-1]
    stem, _, tail = name.rpartition("_")
    is_hash = len(tail) == 8 and all(c in "0123456789abcdef" for c in tail)
    return stem if is_hash else name


def measure(source: str, arch: int) -> list[dict]:
    """Every kernel of the step's modules in the checkout at `source`, compiled for `arch`."""
    sys.path.insert(0, source)
    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    from soil.contact import ContactLaw
    from soil.integrator import integrator_kernels
    from soil.neighbours import neighbour_kernels
    from soil.precision import PRECISIONS, get_precision
    from soil.solver import contact_kernels

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for law_name, law in (("friction", ContactLaw()), ("friction+rolling", ContactLaw(rolling=True))):
            for precision in PRECISIONS:
                p = get_precision(precision)
                for factory in (contact_kernels, integrator_kernels, neighbour_kernels):
                    kernels = factory(p.hi, p.mid, p.lo, law)
                    module = next(v.module for v in vars(kernels).values() if isinstance(v, wp.Kernel))
                    block = module.options["block_dim"]  # the module's block size: its launches' (soil.solver)
                    target = os.path.join(folder, module.name)
                    paths = wp.compile_aot_module(module, arch=arch, module_dir=target, use_ptx=False)
                    for path in (str(q) for q in paths):
                        for name, figures in cubin_kernels(path).items():
                            warps = resident_warps(figures["registers"], figures["shared_bytes"], block)
                            rows.append(
                                {
                                    "kernel": _short(name),
                                    "law": law_name,
                                    "precision": precision,
                                    **figures,
                                    "block_dim": block,
                                    "warps_per_sm": warps,
                                    "warps_per_sm_in_blocks_of_256": resident_warps(
                                        figures["registers"], figures["shared_bytes"]
                                    ),
                                }
                            )
    return rows


def table(rows: list[dict], law: str) -> str:
    """A markdown table: per kernel, registers / stack / resident warps in each precision."""
    kernels = sorted({r["kernel"] for r in rows if r["law"] == law})
    lines = [
        f"| kernel ({law}) | single: registers, stack [B], warps/SM | mixed | double |",
        "|---|---|---|---|",
    ]
    for kernel in kernels:
        cells = []
        for precision in ("single", "mixed", "double"):
            found = [r for r in rows if r["kernel"] == kernel and r["law"] == law and r["precision"] == precision]
            cells.append(
                ", ".join(
                    f"{r['registers']}, {r['stack_bytes']}, {r['warps_per_sm']}"
                    + (f" (blocks of {r['block_dim']})" if r["block_dim"] != BLOCK_DIM else "")
                    for r in found
                )
                or "-"
            )
        lines.append(f"| {kernel} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default=ROOT, help="checkout whose soil package to compile")
    parser.add_argument("--compare", help="another checkout: its kernels too, before this one's")
    parser.add_argument("--arch", type=int, default=ARCH, help="CUDA architecture (90: H100, H200)")
    parser.add_argument(
        "--json", action="store_true", help="print the rows as one JSON line (with --compare: [{checkout, rows}, ...])"
    )
    args = parser.parse_args(argv)
    if args.compare:  # each checkout compiled in a process of its own (its own soil package and kernel cache)
        compared = []
        for source in (os.path.abspath(args.compare), ROOT):
            command = [sys.executable, os.path.abspath(__file__), "--source", source, "--arch", str(args.arch)]
            if args.json:
                done = subprocess.run([*command, "--json"], check=True, stdout=subprocess.PIPE, text=True)
                compared.append({"checkout": source, "rows": json.loads(done.stdout.splitlines()[-1])})
                continue
            print(f"## {source}\n", flush=True)
            subprocess.run(command, check=True)
        if args.json:
            print(json.dumps(compared))  # the compared checkout's rows first, then this one's
        return
    rows = measure(os.path.abspath(args.source), args.arch)
    if args.json:
        print(json.dumps(rows))
        return
    print(
        f"sm_{args.arch}, blocks of {BLOCK_DIM} threads unless named; per kernel: registers per thread, "
        "stack [B], warps resident per SM\n"
    )
    for law in ("friction", "friction+rolling"):
        print(table(rows, law) + "\n")


if __name__ == "__main__":
    main()
