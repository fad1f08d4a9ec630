"""Carry Warp's compiled MuJoCo Warp kernels from one lent GPU machine to the next.

A fresh GPU machine spends ~4-6 minutes of a 15-minute window compiling MuJoCo Warp's kernels
(``results/gpu/race/window-1``: ~390 s from the start of the race to its first update). Warp keeps
what it compiled in its kernel cache (``~/.cache/warp/<version>/``, one folder per module); a
module whose binary (``.cubin``/``.ptx``) and ``.meta`` are there is loaded instead of compiled.
The machine and its disk go back after each window, so the cache is brought back here in slices
and carried to the next machine like the Warp parts (``results/gpu/LEDGER.md``, "The kernel cache").
Only the binaries and their metadata travel: the generated CUDA sources Warp also keeps are not read
on a cache hit.

Standard library only (it runs on the GPU machine before anything is installed)::

    python3 benchmarks/gpu_kernel_cache.py send 0          # device, after the work: slices 0-3 into $OUT
    python3 benchmarks/gpu_kernel_cache.py send 1          # device, next job if it said so: slices 4-7
    python3 benchmarks/gpu_kernel_cache.py collect /work/.device/7 /work/.device/8 --into .gpu/kernels   # here
    # next window, a job per group before the last: carry .gpu/kernels/k0, run `mkdir -p /tmp/gpu/kernels && cp .gpu/kernels/k0/* /tmp/gpu/kernels/`
    python3 benchmarks/gpu_kernel_cache.py restore /tmp/gpu/kernels   # device, before the work (gpu_session.sh does it)

A job brings back at most 64 MiB in files of at most 16 MiB, hence slices of 15 MiB, four per job;
a job carries 64 MiB with the project's tracked files (~24 MiB), hence two slices per carrying job
(``collect`` groups them so: ``k0``, ``k1``, ...).
The binaries are for the GPU's architecture (sm_90 on both the H100 and the H200); a cache from
another architecture or Warp version is simply not hit, and Warp compiles as before.
"""

from __future__ import annotations

import argparse
import io
import lzma
import os
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

SLICE_BYTES = 15 * 1024 * 1024
SLICES_PER_JOB = 4
#: slices a job carries to the device beside the project's tracked files (64 MiB in all)
SLICES_PER_CARRY = 2
PREFIX = "kernels.tar.xz."
#: files Warp reads on a cache hit (the module's binary and its metadata)
KEPT_SUFFIXES = (".cubin", ".ptx", ".meta", ".o", ".so", ".dll")


def default_cache() -> Path:
    """Warp's kernel cache root: ``WARP_CACHE_PATH`` when set (Warp's own override), else ``~/.cache/warp``."""
    return Path(os.environ.get("WARP_CACHE_PATH") or Path.home() / ".cache" / "warp")


def pack(cache: Path, staging: Path, slice_bytes: int = SLICE_BYTES) -> list[Path]:
    """Write the cache's binaries as an xz tar cut in ``slice_bytes`` slices into ``staging`` (once)."""
    done = sorted(staging.glob(PREFIX + "*"))
    if done:
        return done
    if not cache.is_dir():
        raise SystemExit(f"no Warp kernel cache at {cache}: nothing was compiled on this machine yet")
    staging.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    kept = 0
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        for path in sorted(cache.rglob("*")):
            if path.is_file() and path.name.endswith(KEPT_SUFFIXES):
                tar.add(path, arcname=str(path.relative_to(cache)))
                kept += 1
    packed = compress(buffer.getvalue())
    for index, start in enumerate(range(0, len(packed), slice_bytes)):
        (staging / f"{PREFIX}{index:02d}").write_bytes(packed[start : start + slice_bytes])
    print(f"[kernel-cache] {kept} files of {cache}: {len(buffer.getvalue()) / 2**20:.1f} MiB -> {len(packed) / 2**20:.1f} MiB xz")
    return sorted(staging.glob(PREFIX + "*"))


def compress(raw: bytes) -> bytes:
    """xz with every core when the ``xz`` tool is there (seconds), else Python's lzma at a lighter preset."""
    if shutil.which("xz"):
        return subprocess.run(["xz", "-T0", "-6", "-c"], input=raw, capture_output=True, check=True).stdout
    return lzma.compress(raw, preset=3)


def send(job: int, cache: Path, staging: Path, out: Path, slice_bytes: int = SLICE_BYTES) -> None:
    """Copy the ``job``-th group of ``SLICES_PER_JOB`` slices into ``out`` (``$OUT``: what comes back)."""
    slices = pack(cache, staging, slice_bytes)
    group = slices[job * SLICES_PER_JOB : (job + 1) * SLICES_PER_JOB]
    out.mkdir(parents=True, exist_ok=True)
    for path in group:
        shutil.copy2(path, out / path.name)
    jobs = -(-len(slices) // SLICES_PER_JOB)
    print(f"[kernel-cache] slices {[p.name[-2:] for p in group]} of {len(slices)} into {out}", end="")
    print(f"; run `send {job + 1}` in the next job" if job + 1 < jobs else "; that was the last")


def collect(folders: list[Path], into: Path) -> None:
    """Gather the slices that came back (the runs' ``files_at`` folders) into ``into/k0``, ``into/k1``, ...
    of ``SLICES_PER_CARRY`` slices each, one folder per carrying job; refuse a gap."""
    found = {p.name: p for folder in folders for p in folder.glob(PREFIX + "*")}
    indices = sorted(int(name[len(PREFIX) :]) for name in found)
    if not indices or indices != list(range(len(indices))):
        raise SystemExit(f"the folders hold slices {indices}: some are missing (run `send` again for their group)")
    shutil.rmtree(into, ignore_errors=True)
    for name, path in found.items():
        group = into / f"k{int(name[len(PREFIX) :]) // SLICES_PER_CARRY}"
        group.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, group / name)
    total = sum(p.stat().st_size for p in found.values())
    groups = sorted(p.name for p in into.iterdir())
    print(f"[kernel-cache] {len(indices)} slices, {total / 2**20:.1f} MiB in {into}: carry {', '.join(groups)}, one job each")


def restore(folder: Path, cache: Path) -> None:
    """Unpack the slices in ``folder`` into Warp's cache; a missing slice is reported and nothing is written."""
    slices = sorted(folder.rglob(PREFIX + "*"), key=lambda p: p.name)
    indices = [int(p.name[len(PREFIX) :]) for p in slices]
    if not slices or indices != list(range(len(slices))):
        print(f"[kernel-cache] {folder} holds slices {indices}: incomplete, Warp compiles as usual", file=sys.stderr)
        return
    data = lzma.decompress(b"".join(p.read_bytes() for p in slices))
    cache.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        tar.extractall(cache, filter="data")
        count = len(tar.getmembers())
    print(f"[kernel-cache] {count} files restored into {cache}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cache", type=Path, default=None, help="Warp's kernel cache (default: WARP_CACHE_PATH or ~/.cache/warp)")
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser("send", help="on the device: put one job's slices into $OUT")
    s.add_argument("job", type=int)
    s.add_argument("--staging", type=Path, default=Path("/tmp/kernel-cache"))
    s.add_argument("--slice-mib", type=float, default=SLICE_BYTES / 2**20, help="slice size (a returned file is at most 16 MiB)")
    c = sub.add_parser("collect", help="here: gather the slices that came back")
    c.add_argument("folders", type=Path, nargs="+")
    c.add_argument("--into", type=Path, default=Path(".gpu/kernels"))
    r = sub.add_parser("restore", help="on the device: unpack carried slices into Warp's cache")
    r.add_argument("folder", type=Path)
    args = parser.parse_args()
    cache = args.cache or default_cache()
    if args.command == "send":
        out = os.environ.get("OUT")
        if not out:
            raise SystemExit("send runs on the device machine, which sets OUT (the folder that comes back)")
        send(args.job, cache, args.staging, Path(out), int(args.slice_mib * 2**20))
    elif args.command == "collect":
        collect(args.folders, args.into)
    else:
        restore(args.folder, cache)


if __name__ == "__main__":
    main()
