"""The GPU ledger's kernel-cache carrier (``benchmarks/gpu_kernel_cache.py``), run as on the two machines."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu_kernel_cache.py"


def carrier(*args: str, out: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, **({"OUT": str(out)} if out else {})}
    return subprocess.run([sys.executable, str(SCRIPT), *args], env=env, capture_output=True, text=True, check=True)


def test_a_kernel_cache_sent_in_jobs_and_restored_elsewhere_gives_back_its_binaries_only(tmp_path):
    """Two modules of a Warp cache go through send (two jobs' worth of slices), collect and restore:
    their binaries and metadata arrive byte for byte; the generated sources, not read on a cache hit,
    stay behind; a restore missing a slice writes nothing."""
    cache = tmp_path / "device-1" / "warp"
    blobs = {}
    for module in ("wp_collision_ab12", "wp_solver_cd34"):
        folder = cache / "1.19.0" / module
        folder.mkdir(parents=True)
        blobs[f"1.19.0/{module}/{module}.sm90.cubin"] = os.urandom(1_200_000)  # incompressible: several slices
        blobs[f"1.19.0/{module}/{module}.meta"] = b'{"shared_memory_bytes": {}}'
        (folder / f"{module}.cu").write_text("// generated source")
    for name, data in blobs.items():
        (cache / name).write_bytes(data)

    staging = tmp_path / "staging"
    first = carrier("--cache", str(cache), "send", "0", "--staging", str(staging), "--slice-mib", "0.5", out=tmp_path / "job-1")
    assert "run `send 1` in the next job" in first.stdout
    carrier("--cache", str(cache), "send", "1", "--staging", str(staging), "--slice-mib", "0.5", out=tmp_path / "job-2")
    carried = tmp_path / "carried"
    carrier("collect", str(tmp_path / "job-1"), str(tmp_path / "job-2"), "--into", str(carried))
    # 2.4 MB in 0.5 MiB slices: four came back in the first job, one in the second; carried two per job
    assert sorted(len(list(group.iterdir())) for group in carried.iterdir()) == [1, 2, 2]

    fresh = tmp_path / "device-2" / "warp"
    carrier("--cache", str(fresh), "restore", str(carried))
    assert {str(p.relative_to(fresh)): p.read_bytes() for p in fresh.rglob("*") if p.is_file()} == blobs

    # a set missing a slice -- in the middle, or the last one, whose job was never run -- is refused by
    # collect and, carried anyway, restores nothing (Warp compiles as it would have)
    for lost in (2, 4):
        returned = tmp_path / f"returned-without-{lost}"
        returned.mkdir()
        for path in [*(tmp_path / "job-1").iterdir(), *(tmp_path / "job-2").iterdir()]:
            if not path.name.split(".")[2].startswith(f"{lost:02d}-of-"):
                (returned / path.name).write_bytes(path.read_bytes())
        refused = subprocess.run(
            [sys.executable, str(SCRIPT), "collect", str(returned), "--into", str(tmp_path / "never")], capture_output=True, text=True
        )
        assert refused.returncode != 0 and f"misses slice(s) [{lost}] of 5" in refused.stderr + refused.stdout
        other = tmp_path / f"device-without-{lost}" / "warp"
        result = carrier("--cache", str(other), "restore", str(returned))
        assert "Warp compiles as usual" in result.stderr and not other.exists()
