"""The official UNIMAL robot sets (unimals_100), fetched once into a local cache.

MetaMorph, ModuMorph and HyperDistill train on the 100 official training robots and test zero-shot
on held-out robots. The project does not ship them; ``python -m unimal_envs.morphology fetch``
downloads them from the public archive of the ModuMorph / HyperDistill authors' repository, pinned
to one commit (:data:`DEFAULT_SOURCE`), into ``$UNIMAL_DATA`` (default
``$XDG_CACHE_HOME/unimal_envs``, i.e. ``~/.cache/unimal_envs``). After that the sets are names like
``"train"``: ``gym.make(..., morphologies="unimals100-train")``, profiles' ``train_set`` /
``novel_set``, and the CLIs.

=======================  ==============================  =======  ====================================
set name                 folder in the archive           robots   notes
=======================  ==============================  =======  ====================================
``unimals100-train``     ``data/train``                  100      the official training robots
                                                                  (checksums verified)
``unimals100-test``      ``data/test``                   97       the official held-out robots, the novel
                                                                  split of zero-shot evaluation: the
                                                                  folder's 102 less the 5 that are byte
                                                                  copies of training robots
                                                                  (:data:`TEST_BYTE_COPIES`), left out
``unimals100-mutants``   ``data/train_mutate_1000``      1000     mutated training robots (HyperDistill)
=======================  ==============================  =======  ====================================

Each set lands in ``<cache>/<set name>/{xml,metadata}`` (the unimals_100 layout) with a
``MANIFEST.json`` (source, per-file SHA-256) written last. Fetching is

* **verified**: the expected number of robots in the archive, a metadata file per robot, every robot loads through
  :func:`~unimal_envs.morphology.loader.load_morphology`, and the training robots match the
  checksums shipped in ``unimal_envs/data/unimals100_train.sha256``;
* **atomic**: a set is unpacked and verified in a staging folder of the cache and renamed into
  place only when complete, so an interrupted or failed fetch leaves no half set;
* **idempotent**: sets already in the cache are not fetched again (``force=True`` re-fetches);
* **confined**: only regular files under the three folders are extracted; an archive member with
  an absolute path or a ``..`` component is refused.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import re
import shutil
import tarfile
import tempfile
import time
import urllib.error
import urllib.request
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path, PurePosixPath

from unimal_envs.morphology.cache import (  # noqa: F401 -- where a set lives and whether it is there; re-exported
    MANIFEST,
    OFFICIAL_SETS,
    SHORT_NAMES,
    TEST_BYTE_COPIES,
    OfficialSet,
    cache_root,
    fetch_command,
    is_cached,
    official_set_dir,
)
from unimal_envs.morphology.errors import MorphologyError

#: Commit of ``MasterXiong/Universal-Morphology-Control`` the default source is pinned to.
PINNED_COMMIT = "18c0516c0e133ba960e2f5b56c0817adc8983ec9"
DEFAULT_SOURCE = f"https://github.com/MasterXiong/Universal-Morphology-Control/archive/{PINNED_COMMIT}.tar.gz"
_CHECKSUMS = Path(__file__).resolve().parent.parent / "data" / "unimals100_train.sha256"


class FetchError(MorphologyError):
    """Fetching or verifying an official set failed (nothing was installed)."""


def training_checksums() -> dict[str, str]:
    """``{"xml/<name>.xml": sha256, "metadata/<name>.json": sha256}`` of the official training set."""
    table = {}
    for line in _CHECKSUMS.read_text().splitlines():
        digest, rel = line.split(maxsplit=1)
        table[rel] = digest
    return table


# ------------------------------------------------------------------------------------ sources
def _members(source_root: Path | None, tar: tarfile.TarFile | None) -> Iterator[tuple[str, Callable[[], bytes]]]:
    """(relative posix path, reader) of every regular file of a directory or an archive."""
    if source_root is not None:
        for path in sorted(source_root.rglob("*")):
            if path.is_file() and not path.is_symlink():
                yield path.relative_to(source_root).as_posix(), path.read_bytes
        return
    for member in tar:
        name = member.name
        parts = PurePosixPath(name).parts
        if name.startswith("/") or re.match(r"^[A-Za-z]:", name) or ".." in parts:
            raise FetchError(f"archive member '{name}' has an absolute path or a '..' component; refusing to unpack")
        if member.isfile():
            yield name, lambda m=member: tar.extractfile(m).read()


def _set_relative(path: str, folder: str) -> str | None:
    """``xml/<file>`` / ``metadata/<file>`` if ``path`` is a file of set ``folder``, else ``None``.

    Accepted layouts: ``[<top>/]data/<folder>/{xml,metadata}/<file>`` (the repository and GitHub's
    archive of it) and ``[<top>/]<folder>/{xml,metadata}/<file>``.
    """
    parts = PurePosixPath(path).parts
    i = len(parts) - 3
    if i < 0 or parts[i] != folder or parts[i + 1] not in ("xml", "metadata"):
        return None
    prefix = parts[:i]
    if len(prefix) <= 1 or (len(prefix) == 2 and prefix[-1] == "data"):
        return f"{parts[i + 1]}/{parts[i + 2]}"
    return None


def _download(url: str, target: Path, progress: bool) -> None:
    """Stream ``url`` into ``target``; a short read (truncated transfer) is an error."""
    try:
        with urllib.request.urlopen(url, timeout=60) as response, open(target, "wb") as out:  # noqa: S310
            expected = response.headers.get("Content-Length")
            done = 0
            last = time.monotonic()
            while chunk := response.read(1 << 20):
                out.write(chunk)
                done += len(chunk)
                if progress and time.monotonic() - last > 2:
                    print(f"  downloaded {done / 2**20:.1f} MiB", flush=True)
                    last = time.monotonic()
    except (urllib.error.URLError, OSError, ValueError) as err:
        raise FetchError(
            f"could not download {url}: {err}. Without a network, fetch from a copy: the archive of the "
            f"MasterXiong/Universal-Morphology-Control repository at commit {PINNED_COMMIT} (that URL's .tar.gz, "
            "downloaded elsewhere), a checkout of it, or a folder holding train/ and test/ (each with xml/ and metadata/): "
            "`python -m unimal_envs.morphology fetch --source PATH`"
        ) from None
    if expected is not None and done != int(expected):
        raise FetchError(f"download of {url} is truncated: got {done} of {expected} bytes")


def _check_gzip(archive: Path) -> None:
    """Read a gzip archive to its end once: a truncated or damaged stream fails its length/CRC check
    here, whereas tarfile may stop quietly at the first unreadable header."""
    with open(archive, "rb") as f:
        if f.read(2) != b"\x1f\x8b":
            return
    with gzip.open(archive, "rb") as stream:
        while stream.read(1 << 22):
            pass


# ------------------------------------------------------------------------------------ fetching
def _verify(staging: Path, spec: OfficialSet, files: dict[str, bytes]) -> None:
    from unimal_envs.morphology.loader import load_morphology

    xml = sorted(p for p in files if p.startswith("xml/") and p.endswith(".xml"))
    meta = {p.removeprefix("metadata/").removesuffix(".json") for p in files if p.startswith("metadata/")}
    if len(xml) != spec.count:
        raise FetchError(f"{spec.name}: expected {spec.count} robots in data/{spec.folder}/xml, found {len(xml)}")
    missing = [p for p in xml if PurePosixPath(p).stem not in meta]
    if missing:
        raise FetchError(f"{spec.name}: no metadata json for {missing[:5]}")
    if spec.byte_copies:
        copies = byte_copies_of_training(files)
        if copies != spec.byte_copies:
            raise FetchError(f"{spec.name}: the robots that are byte copies of training robots are {copies}, expected {spec.byte_copies}")
    if spec.name == "unimals100-train":
        expected = training_checksums()
        bad = sorted(rel for rel, digest in expected.items() if rel not in files or hashlib.sha256(files[rel]).hexdigest() != digest)
        if bad:
            raise FetchError(f"{spec.name}: {len(bad)} file(s) missing or differing from the official checksums: {bad[:5]}")
    for rel in sorted(files):
        if rel.startswith("metadata/"):
            try:
                json.loads(files[rel])
            except ValueError as err:
                raise FetchError(f"{spec.name}: {rel} is not valid JSON ({err})") from None
    for rel in xml:
        try:
            load_morphology(staging / rel)
        except MorphologyError as err:
            raise FetchError(f"{spec.name}: a robot does not load: {err}") from None


def byte_copies_of_training(files: dict[str, bytes]) -> dict[str, str]:
    """``{robot: training robot}`` for every ``xml/<robot>.xml`` of ``files`` whose bytes are those
    of an official training robot's MJCF (by the shipped SHA-256 checksums)."""
    training = {digest: PurePosixPath(rel).stem for rel, digest in training_checksums().items() if rel.startswith("xml/")}
    copies = {}
    for rel, data in files.items():
        if rel.startswith("xml/") and rel.endswith(".xml"):
            original = training.get(hashlib.sha256(data).hexdigest())
            if original is not None:
                copies[PurePosixPath(rel).stem] = original
    return dict(sorted(copies.items()))


def _install(cache: Path, spec: OfficialSet, files: dict[str, bytes], source: str) -> Path:
    """Write, verify and atomically move one set into the cache (less its byte copies of training robots)."""
    staging = Path(tempfile.mkdtemp(prefix=f".staging-{spec.name}-", dir=cache))
    try:
        for rel, data in files.items():
            target = staging / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        _verify(staging, spec, files)
        left_out = {f"{kind}/{name}.{ext}" for name in spec.byte_copies for kind, ext in (("xml", "xml"), ("metadata", "json"))}
        for rel in left_out:
            (staging / rel).unlink(missing_ok=True)
        kept = {rel: data for rel, data in files.items() if rel not in left_out}
        manifest = {
            "set": spec.name,
            "source": source,
            "folder": f"data/{spec.folder}",
            "robots": spec.robots,
            "left_out": {name: f"byte copy of training robot {original}" for name, original in spec.byte_copies.items()},
            "sha256": {rel: hashlib.sha256(data).hexdigest() for rel, data in sorted(kept.items())},
        }
        (staging / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        final = cache / spec.name
        if final.exists():  # an incomplete leftover (no manifest) or a forced re-fetch
            shutil.rmtree(final)
        os.replace(staging, final)
        return final
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)


def fetch(
    source: str | Path | None = None,
    sets: Iterable[str] = ("train", "test", "mutants"),
    cache: str | Path | None = None,
    force: bool = False,
    progress: bool = False,
) -> dict[str, Path]:
    """Fetch official sets into the cache (see the module docstring).

    :param source: an ``http(s)://`` or ``file://`` URL of a ``.tar.gz`` archive, a local archive, or
        a directory (a checkout of the repository, a folder holding ``<folder>/xml``, or, for one set,
        the set folder itself). Default :data:`DEFAULT_SOURCE`.
    :param sets: short names (``train``, ``test``, ``mutants``) or full set names.
    :param cache: cache folder (default :func:`cache_root`).
    :param force: fetch again even if a set is cached.
    :param progress: print progress.
    :returns: set name -> cached folder.
    :raises FetchError: download, archive or verification failure; nothing half-written remains.
    """
    specs = []
    for s in sets:
        spec = SHORT_NAMES.get(s) or OFFICIAL_SETS.get(s)
        if spec is None:
            raise FetchError(f"unknown official set '{s}'; choose from {list(SHORT_NAMES)}")
        if spec not in specs:
            specs.append(spec)
    root = cache_root(cache)
    root.mkdir(parents=True, exist_ok=True)
    todo = [s for s in specs if force or not is_cached(s.name, root)]
    result = {s.name: root / s.name for s in specs}
    if not todo:
        return result
    source = DEFAULT_SOURCE if source is None else source
    text = str(source)
    download: Path | None = None
    try:
        if re.match(r"^(https?|file)://", text):
            fd, name = tempfile.mkstemp(prefix=".download-", suffix=".tar.gz", dir=root)
            os.close(fd)
            download = Path(name)
            if progress:
                print(f"downloading {text}", flush=True)
            _download(text, download, progress)
            archive: Path | None = download
        else:
            archive = Path(source).expanduser()
            if not archive.exists():
                raise FetchError(f"source {archive} does not exist (give a URL, an archive or a directory)")
        collected: dict[str, dict[str, bytes]] = {s.name: {} for s in todo}
        if archive.is_dir():
            direct = (archive / "xml").is_dir()
            for rel, read in _members(archive, None):
                for spec in todo:
                    inner = _set_relative(rel, spec.folder)
                    if inner is None and direct and len(todo) == 1 and re.match(r"^(xml|metadata)/[^/]+$", rel):
                        inner = rel  # the set folder itself
                    if inner is not None:
                        collected[spec.name][inner] = read()
        else:
            try:
                _check_gzip(archive)
                with tarfile.open(archive, "r:*") as tar:
                    for rel, read in _members(None, tar):
                        for spec in todo:
                            inner = _set_relative(rel, spec.folder)
                            if inner is not None:
                                collected[spec.name][inner] = read()
            except (tarfile.TarError, EOFError, OSError, ValueError, zlib.error) as err:
                if isinstance(err, FetchError):
                    raise
                raise FetchError(f"the archive {text} is truncated or corrupted ({type(err).__name__}: {err})") from None
        for spec in todo:
            if not collected[spec.name]:
                raise FetchError(f"{text} holds no data/{spec.folder}/xml folder (set {spec.name})")
            if progress:
                print(f"verifying {spec.name} ({spec.robots} robots)", flush=True)
            result[spec.name] = _install(root, spec, collected[spec.name], text)
    finally:
        if download is not None and download.exists():
            download.unlink()
    return result
