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
(``collect`` groups them so: ``k0``, ``k1``, ...). Each slice is named after its archive's hash and
the number of slices (``kernels.<hash>.<i>-of-<n>``), so an incomplete or mixed set is refused by
``collect`` and skipped by ``restore``, never half-restored. The binaries are for the GPU's architecture (sm_90 on both the H100 and the H200); a cache from
another architecture or Warp version is simply not hit, and Warp compiles as before.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import lzma
import os
import re
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

SLICE_BYTES = 15 * 1024 * 1024
SLICES_PER_JOB = 4
#: slices a job carries to the device beside the project's tracked files (64 MiB in all)
SLICES_PER_CARRY = 2
#: a slice's name (:func:`slice_name`)
SLICE = re.compile(r"kernels\.([0-9a-f]{8})\.(\d+)-of-(\d+)")
#: files Warp reads on a cache hit (the module's binary and its metadata)
KEPT_SUFFIXES = (".cubin", ".ptx", ".meta", ".o", ".so", ".dll")


def default_cache() -> Path:
    """Warp's kernel cache root: ``WARP_CACHE_PATH`` when set (Warp's own override), else ``~/.cache/warp``."""
    return Path(os.environ.get("WARP_CACHE_PATH") or Path.home() / ".cache" / "warp")


def slice_name(digest: str, index: int, count: int) -> str:
    """``kernels.<first 8 hex digits of the archive's sha256>.<index>-of-<count>``: a slice says which
    archive it belongs to and how many there are, so that a set is known complete or not."""
    return f"kernels.{digest[:8]}.{index:02d}-of-{count:02d}"


def read_set(paths: list[Path]) -> tuple[str, list[Path]]:
    """The one complete archive among ``paths``' slices, ``(digest, slices in order)``.

    :raises ValueError: no slices, slices of several archives, or a missing one (named).
    """
    sets: dict[str, dict[int, Path]] = {}
    counts: dict[str, int] = {}
    for path in paths:
        match = SLICE.fullmatch(path.name)
        if match:
            digest, index, count = match.group(1), int(match.group(2)), int(match.group(3))
            sets.setdefault(digest, {})[index] = path
            counts[digest] = count
    if not sets:
        raise ValueError("no kernel-cache slices")
    if len(sets) > 1:
        raise ValueError(f"slices of {len(sets)} different archives ({', '.join(sorted(sets))}): keep one pack's")
    (digest, found), count = next(iter(sets.items())), next(iter(counts.values()))
    missing = [i for i in range(count) if i not in found]
    if missing:
        raise ValueError(f"archive {digest} misses slice(s) {missing} of {count} (run `send` again for their group)")
    return digest, [found[i] for i in range(count)]


def pack(cache: Path, staging: Path, slice_bytes: int = SLICE_BYTES) -> list[Path]:
    """Write the cache's binaries as an xz tar cut in ``slice_bytes`` slices into ``staging``, once:
    a later call reuses a complete set (written to a temporary folder first, then renamed)."""
    if staging.is_dir():
        try:
            return read_set(sorted(staging.iterdir()))[1]
        except ValueError:
            shutil.rmtree(staging)
    if not cache.is_dir():
        raise SystemExit(f"no Warp kernel cache at {cache}: nothing was compiled on this machine yet")
    buffer = io.BytesIO()
    kept = 0
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        for path in sorted(cache.rglob("*")):
            if path.is_file() and path.name.endswith(KEPT_SUFFIXES):
                tar.add(path, arcname=str(path.relative_to(cache)))
                kept += 1
    packed = compress(buffer.getvalue())
    digest = hashlib.sha256(packed).hexdigest()
    count = -(-len(packed) // slice_bytes)
    partial = staging.with_name(staging.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    for index in range(count):
        (partial / slice_name(digest, index, count)).write_bytes(packed[index * slice_bytes : (index + 1) * slice_bytes])
    os.replace(partial, staging)
    print(
        f"[kernel-cache] {kept} files of {cache}: {len(buffer.getvalue()) / 2**20:.1f} MiB -> {len(packed) / 2**20:.1f} MiB xz, {count} slices"
    )
    return read_set(sorted(staging.iterdir()))[1]


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
    print(f"[kernel-cache] slices {[job * SLICES_PER_JOB + i for i in range(len(group))]} of {len(slices)} into {out}", end="")
    print(f"; run `send {job + 1}` in the next job" if job + 1 < jobs else "; that was the last")


def collect(folders: list[Path], into: Path) -> None:
    """Gather the slices that came back (the runs' ``files_at`` folders) into ``into/k0``, ``into/k1``, ...
    of ``SLICES_PER_CARRY`` slices each, one folder per carrying job; refuse an incomplete set."""
    try:
        digest, slices = read_set([p for folder in folders for p in folder.iterdir()])
    except ValueError as error:
        raise SystemExit(f"[kernel-cache] {error}") from None
    for old in into.glob("k*/kernels.*"):  # an earlier set's slices (nothing else in `into` is touched)
        old.unlink()
    for index, path in enumerate(slices):
        group = into / f"k{index // SLICES_PER_CARRY}"
        group.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, group / path.name)
    total = sum(p.stat().st_size for p in slices)
    groups = sorted({f"k{index // SLICES_PER_CARRY}" for index in range(len(slices))})
    print(
        f"[kernel-cache] archive {digest}: {len(slices)} slices, {total / 2**20:.1f} MiB in {into}: carry {', '.join(groups)}, one job each"
    )


def restore(folder: Path, cache: Path) -> None:
    """Unpack the slices in ``folder`` into Warp's cache. An incomplete or damaged set is reported
    and nothing is written: Warp then compiles as it would have."""
    try:
        digest, slices = read_set(sorted(p for p in folder.rglob("kernels.*") if p.is_file()))
        packed = b"".join(p.read_bytes() for p in slices)
        if hashlib.sha256(packed).hexdigest()[:8] != digest:
            raise ValueError(f"archive {digest}: its slices do not add up to it (damaged in transit?)")
        data = lzma.decompress(packed)
    except (ValueError, lzma.LZMAError) as error:
        print(f"[kernel-cache] {folder}: {error}; Warp compiles as usual", file=sys.stderr)
        return
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
