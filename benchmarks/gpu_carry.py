"""The Python packages the GPU suite needs on a lent GPU machine, packed to travel there.

    python3 benchmarks/gpu_carry.py pack          # here, with network: .gpu_carry/1, .gpu_carry/2, ...
    python3 benchmarks/gpu_carry.py check         # which parts have arrived, and whether their kernels
                                                  # are this tree's (soil/ unchanged since the pack)
    python3 benchmarks/gpu_carry.py install       # there, once every part is in: into .gpu_site
                                                  # and the suite's kernels into .gpu_kernels

The lent machine (one H200; Python 3.12; numpy, h5py, scipy, matplotlib, pytest there) reaches no
package index and lacks Warp, MuJoCo and pydantic, so they travel with the working tree, which may
carry at most 64 MiB per call. Warp's wheel alone is 142 MiB (its CUDA library, warp.so, 285 MiB
unpacked, compresses to 74 MiB with xz): no single call can carry it. `pack` downloads the wheels
for the machine's Python, recompresses Warp's two native libraries with xz, puts everything in one
tar and cuts it into parts that each fit a call beside the working tree. One call per part carries
it (`carry: [".gpu_carry/K"]`); an ignored folder a call brought stays on the machine while it is
held (it goes back 30 s after a call), so the calls follow one another at once, and the last one
installs and runs (BENCHMARKS.md, "Running the GPU suite on a lent machine").

The parts also carry the suite's CUDA kernels, compiled here for the machine's architecture (sm_90)
without a GPU: `gpu_suite.py --small --device cpu --compile-for-arch 90` loads every Warp module the
suite's code paths use, then compiles each to machine code into a kernel cache (NVRTC needs no GPU;
the cache key is a module's hash, the same on every device). Warp's cache starts empty on a fresh
machine and compiles each module on its first use there, device time spent compiling; with
WARP_CACHE_PATH at the installed kernels it loads them instead.

Pinned to the versions installed here, so the machine runs what the tests passed on.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.metadata
import io
import json
import lzma
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CARRY = os.path.join(ROOT, ".gpu_carry")
SITE = os.path.join(ROOT, ".gpu_site")
KERNELS = os.path.join(ROOT, ".gpu_kernels")
"""Where `install` puts the carried kernel cache (WARP_CACHE_PATH there)."""
ARCH = 90
"""The lent machine's CUDA architecture (H100 and H200: sm_90)."""
MANIFEST = "manifest.json"
CALL_LIMIT = 64 * 2**20
"""What one call may carry, the working tree included [bytes]."""
MARGIN = 4 * 2**20
"""Room left in each call for files the tree gains before the calls [bytes]."""
PACKAGES = (
    "warp-lang",
    "pydantic",
    "pydantic-core",
    "annotated-types",
    "typing-inspection",
    "typing-extensions",
    "tomli-w",
    "mujoco",
    "mujoco-core",
)
"""What the lent machine lacks of what cosim, soil, rover_models and the suite import (its image's
own numpy, h5py, scipy, filelock, tqdm, matplotlib and pytest serve). MuJoCo's viewer and renderer
(mujoco-studio, glfw, pyopengl: 15 MiB) stay behind: the suite draws nothing."""
NATIVE = ("warp/bin/warp.so", "warp/bin/warp-clang.so")
"""Warp's native libraries, travelling xz-compressed (the rest of its wheel as a zip)."""
LEFT_BEHIND = ("warp/examples/", "warp/tests/")
"""Parts of Warp's wheel nothing here imports (4 MiB)."""
KERNEL_SOURCES = "soil"
"""The folder whose Python files define every Warp kernel the suite loads: a carried kernel is looked
up by its module's hash, so kernels packed from other sources than the tree's are not found there."""
DEVICE_PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64")


def tree_bytes() -> int:
    """Bytes of what travels with every call: tracked files and untracked ones git does not ignore."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        check=True,
    ).stdout
    paths = [os.path.join(ROOT, p) for p in listed.decode().split("\0") if p]
    return sum(os.path.getsize(p) for p in paths if os.path.isfile(p))


def download(python_version: str, into: str) -> list[str]:
    """The wheels of PACKAGES, at the versions installed here, for CPython `python_version` on x86-64 Linux."""
    pins = [f"{name}=={importlib.metadata.version(name)}" for name in PACKAGES]
    platforms = [arg for p in DEVICE_PLATFORMS for arg in ("--platform", p)]
    subprocess.run(
        [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--implementation", "cp",
         "--python-version", python_version, *platforms, "-d", into, *pins],
        check=True,
    )  # fmt: skip
    return sorted(os.path.join(into, f) for f in os.listdir(into) if f.endswith(".whl"))


def xz(data: bytes) -> bytes:
    """xz-compressed `data` (by the xz program on every core when there is one, else by lzma)."""
    if shutil.which("xz"):
        return subprocess.run(["xz", "-9", "-T0", "-c"], input=data, capture_output=True, check=True).stdout
    return lzma.compress(data, preset=9)


def compile_kernels(arch: int, into: str) -> str:
    """A Warp kernel cache at `into` holding the GPU suite's modules compiled for CUDA architecture
    `arch` (the suite run small on this CPU, then every module it loaded compiled for `arch`)."""
    suite = os.path.join(ROOT, "benchmarks", "gpu_suite.py")
    subprocess.run(
        [sys.executable, suite, "--small", "--device", "cpu", "--out", os.path.join(into, "suite"),
         "--compile-for-arch", str(arch)],
        cwd=ROOT, env={**os.environ, "WARP_CACHE_PATH": into}, check=True, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    return into


def kernel_files(cache: str, arch: int) -> list[str]:
    """The files of a Warp kernel cache a CUDA device of architecture `arch` loads: each module's
    machine code and its metadata (paths relative to the cache's root)."""
    found = []
    for folder, _, files in os.walk(cache):
        cubins = [f for f in files if f.endswith(f".sm{arch}.cubin")]
        for name in cubins + ([f for f in files if f.endswith(".meta")] if cubins else []):
            found.append(os.path.relpath(os.path.join(folder, name), cache))
    return sorted(found)


def sources_digest(root: str = ROOT) -> str:
    """sha256 over the Python files under `root`/KERNEL_SOURCES (paths and contents, in sorted order)."""
    digest = hashlib.sha256()
    base = os.path.join(root, KERNEL_SOURCES)
    files = sorted(
        os.path.relpath(os.path.join(folder, name), base)
        for folder, _, names in os.walk(base)
        for name in names
        if name.endswith(".py")
    )
    for name in files:
        digest.update(name.encode() + b"\0")
        with open(os.path.join(base, name), "rb") as f:
            digest.update(f.read() + b"\0")
    return digest.hexdigest()


def stale_kernels(manifest: dict, root: str = ROOT) -> str | None:
    """Why the carried kernels will not serve the tree at `root` (packed from other kernel sources), or
    None when they will (or when none were packed)."""
    if not manifest.get("kernels_arch"):
        return None
    packed = manifest.get("kernel_sources")
    if packed is None:
        return "the pack does not say which sources its kernels were compiled from (packed before it did): pack again"
    here = sources_digest(root)
    if packed == here:
        return None
    return (
        f"the kernels were packed from other sources than {os.path.join(root, KERNEL_SOURCES)}/ (sha256 "
        f"{packed[:12]} packed, {here[:12]} here): Warp compiles every changed module on its first use, on "
        "the device's time; pack again to carry them compiled"
    )


def pack(
    python_version: str,
    out: str = CARRY,
    wheels: list[str] | None = None,
    limit: int | None = None,
    kernels: str | None = None,
    arch: int = ARCH,
    kernel_sources: str | None = None,
) -> dict:
    """Write the parts into `out`/1, `out`/2, ... (each with the manifest); returns the manifest.
    `kernels`: a Warp kernel cache whose modules for `arch` travel too (compile_kernels);
    `kernel_sources`: the sources_digest of the tree they were compiled from (taken before compiling;
    None: this tree's now)."""
    with tempfile.TemporaryDirectory() as scratch:
        wheels = wheels or download(python_version, scratch)
        blob = os.path.join(scratch, "carry.tar")
        with tarfile.open(blob, "w") as tar:
            if kernels:  # xz: machine code compresses about 7-fold
                bundle = io.BytesIO()
                with tarfile.open(fileobj=bundle, mode="w") as cache:
                    for name in kernel_files(kernels, arch):
                        cache.add(os.path.join(kernels, name), arcname=name)
                _add(tar, "kernels.tar.xz", xz(bundle.getvalue()))
            for wheel in wheels:
                name = os.path.basename(wheel)
                if not name.startswith("warp_lang-"):
                    tar.add(wheel, arcname=f"wheels/{name}")
                    continue
                rest = io.BytesIO()
                with zipfile.ZipFile(wheel) as source, zipfile.ZipFile(rest, "w", zipfile.ZIP_DEFLATED) as kept:
                    for item in source.infolist():
                        if item.filename.startswith(LEFT_BEHIND):
                            continue
                        if item.filename in NATIVE:
                            _add(tar, f"warp/{item.filename}.xz", xz(source.read(item)))
                        else:
                            kept.writestr(item, source.read(item))
                _add(tar, "warp/rest.zip", rest.getvalue())
        limit = limit or CALL_LIMIT - tree_bytes() - MARGIN
        size = os.path.getsize(blob)
        count = -(-size // limit)
        if os.path.isdir(out):
            shutil.rmtree(out)
        manifest = {
            "python_version": python_version,
            "bytes": size,
            "kernels_arch": arch if kernels else None,
            "kernel_sources": (kernel_sources or sources_digest()) if kernels else None,
            "parts": [],
        }
        with open(blob, "rb") as f:
            for k in range(1, count + 1):
                piece = f.read(-(-size // count))
                os.makedirs(os.path.join(out, str(k)))
                with open(os.path.join(out, str(k), "carry.tar.part"), "wb") as part:
                    part.write(piece)
                manifest["parts"].append({"bytes": len(piece), "sha256": hashlib.sha256(piece).hexdigest()})
        for k in range(1, count + 1):
            with open(os.path.join(out, str(k), MANIFEST), "w") as f:
                json.dump({**manifest, "part": k}, f, indent=1)
    return manifest


def _add(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    tar.addfile(info, io.BytesIO(data))


class CarryError(RuntimeError):
    """A part is missing or damaged: which one, and which call brings it."""


def check(out: str = CARRY) -> dict:
    """The manifest, once every part under `out` is present and intact; else CarryError naming the parts."""
    folders = sorted(os.listdir(out)) if os.path.isdir(out) else []
    present = [m for m in (os.path.join(out, k, MANIFEST) for k in folders) if os.path.isfile(m)]
    if not present:
        raise CarryError(f"no part in {out}: each call carries one (carry: ['.gpu_carry/K'])")
    with open(present[0]) as f:
        manifest = json.load(f)
    problems = []
    for k, part in enumerate(manifest["parts"], start=1):
        path = os.path.join(out, str(k), "carry.tar.part")
        if not os.path.isfile(path):
            problems.append(f"part {k} is missing ({path}): a call with carry ['.gpu_carry/{k}'] brings it")
            continue
        with open(path, "rb") as f:
            digest = hashlib.sha256(f.read()).hexdigest()
        if digest != part["sha256"]:
            problems.append(f"part {k} ({path}) is damaged: sha256 {digest}, packed {part['sha256']}")
    if problems:
        raise CarryError("; ".join(problems))
    return manifest


def install(out: str = CARRY, target: str = SITE, kernels: str = KERNELS) -> list[str]:
    """Unpack the parts into `target` (a folder for PYTHONPATH), and the kernel cache they carry into
    `kernels` (a folder for WARP_CACHE_PATH); returns what was installed."""
    manifest = check(out)
    if manifest["python_version"] != f"{sys.version_info[0]}.{sys.version_info[1]}":
        raise CarryError(f"packed for Python {manifest['python_version']}, this is {sys.version.split()[0]}")
    blob = io.BytesIO()
    for k in range(1, len(manifest["parts"]) + 1):
        with open(os.path.join(out, str(k), "carry.tar.part"), "rb") as f:
            blob.write(f.read())
    blob.seek(0)
    for folder in (target, kernels):
        if os.path.isdir(folder):
            shutil.rmtree(folder)
    os.makedirs(target)
    with tempfile.TemporaryDirectory() as scratch, tarfile.open(fileobj=blob) as tar:
        tar.extractall(scratch, filter="data")
        modules = 0
        if manifest.get("kernels_arch"):
            with open(os.path.join(scratch, "kernels.tar.xz"), "rb") as f:
                bundle = io.BytesIO(lzma.decompress(f.read()))
            with tarfile.open(fileobj=bundle) as cache:
                cache.extractall(kernels, filter="data")
            modules = len(kernel_files(kernels, manifest["kernels_arch"])) // 2
        wheels = sorted(os.path.join(scratch, "wheels", w) for w in os.listdir(os.path.join(scratch, "wheels")))
        pip = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile"]
        subprocess.run([*pip, "--target", target, *wheels], check=True)
        with zipfile.ZipFile(os.path.join(scratch, "warp", "rest.zip")) as rest:
            rest.extractall(target)
        for native in NATIVE:
            with open(os.path.join(scratch, "warp", native + ".xz"), "rb") as f:
                data = lzma.decompress(f.read())
            os.makedirs(os.path.dirname(os.path.join(target, native)), exist_ok=True)
            with open(os.path.join(target, native), "wb") as f:
                f.write(data)
    done = [os.path.basename(w) for w in wheels] + ["warp-lang (" + ", ".join(NATIVE) + " from xz)"]
    return done + ([f"{modules} Warp modules for sm_{manifest['kernels_arch']} into {kernels}"] if modules else [])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("action", choices=("pack", "check", "install"))
    parser.add_argument("--python-version", default="3.12", help="pack: the lent machine's Python (major.minor)")
    parser.add_argument("--carry", default=CARRY, help="the parts' folder")
    parser.add_argument("--target", default=SITE, help="install: the folder to put on PYTHONPATH")
    parser.add_argument("--kernels", default=KERNELS, help="install: the folder to put in WARP_CACHE_PATH")
    parser.add_argument(
        "--arch", type=int, default=ARCH, help="pack: the CUDA architecture to compile the suite's kernels for"
    )
    parser.add_argument("--no-kernels", action="store_true", help="pack: no compiled kernels (the machine compiles)")
    args = parser.parse_args(argv)
    try:
        if args.action == "pack":
            sources = sources_digest()  # before compiling: a source edited meanwhile then reads as stale
            with tempfile.TemporaryDirectory() as scratch:
                kernels = None if args.no_kernels else compile_kernels(args.arch, scratch)
                manifest = pack(
                    args.python_version, args.carry, kernels=kernels, arch=args.arch, kernel_sources=sources
                )
            sizes = ", ".join(f"{p['bytes'] / 2**20:.1f} MiB" for p in manifest["parts"])
            tree = tree_bytes() / 2**20
            print(f"{len(manifest['parts'])} parts in {args.carry} ({sizes}), each beside {tree:.1f} MiB of tree")
        elif args.action == "check":
            manifest = check(args.carry)
            stale = stale_kernels(manifest)
            print(f"all {len(manifest['parts'])} parts present and intact" + (f"; {stale}" if stale else ""))
        else:
            for name in install(args.carry, args.target, args.kernels):
                print(f"installed {name}")
            stale = stale_kernels(check(args.carry))
            if stale:
                print(f"gpu_carry: {stale}", file=sys.stderr)
            print(f"export PYTHONPATH={args.target} WARP_CACHE_PATH={args.kernels}")
    except CarryError as error:
        print(f"gpu_carry: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
