"""Pack the CSV logs of a recorded run's finished stages, so that the run fits the repository.

    python tools/pack_logs.py results/cpu100                 # what packing would save (writes nothing)
    python tools/pack_logs.py --write results/cpu100/transfer

A 100-robot run writes tens of MB of CSV (a transfer run's ``eval.csv`` holds every robot's episodes at
every evaluation; ``progress.csv`` every PPO update), more than the repository's tracked-size limit
allows (``tests/test_tree_size.py``). Packing gzips ``progress.csv``, ``eval.csv`` and ``returns.csv``
into ``<name>.gz`` (deterministic: no timestamp, so a re-pack is byte-identical) and removes the plain
file after checking that the packed one reads back byte for byte. Every reader of the pipeline takes
either form (``divmorph.pipeline.files.log_file``), and a plain file written later wins over its
packed twin. Only finished stages are packed -- a folder with ``done.json`` at or above the file --
because a running stage appends to its logs.
"""

from __future__ import annotations

import argparse
import gzip
import io
from pathlib import Path

NAMES = ("progress.csv", "eval.csv", "returns.csv")


def packable(root: Path) -> list[Path]:
    """The plain CSV logs under ``root`` whose stage has finished."""
    found = []
    for path in sorted(p for name in NAMES for p in root.rglob(name)):
        if any((folder / "done.json").is_file() for folder in path.parents if folder == root or root in folder.parents):
            found.append(path)
    return found


def pack(path: Path) -> bytes:
    """The gzip bytes of ``path`` (no name, no timestamp: the same input gives the same bytes)."""
    buffer = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=buffer, compresslevel=9, mtime=0) as f:
        f.write(path.read_bytes())
    return buffer.getvalue()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path, help="run or stage folders to pack (searched recursively)")
    parser.add_argument("--write", action="store_true", help="write the .gz files and remove the plain ones")
    args = parser.parse_args()
    before = after = 0
    for root in args.folders:
        for path in packable(root):
            packed = pack(path)
            if gzip.decompress(packed) != path.read_bytes():  # never lose a log to a bad pack
                raise SystemExit(f"{path}: the packed bytes do not read back; nothing written for it")
            before, after = before + path.stat().st_size, after + len(packed)
            if args.write:
                target = path.with_name(path.name + ".gz")
                target.write_bytes(packed)
                path.unlink()
    verb = "packed" if args.write else "would pack"
    print(f"{verb} {before:,} B of CSV logs into {after:,} B ({before / max(after, 1):.1f}x smaller)")


if __name__ == "__main__":
    main()
