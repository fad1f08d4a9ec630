"""The project's shipped models, for a pip install that has no git checkout.

The trained models of the 100-robot run live in the repository (``results/cpu100/``), not in the
wheel. ``divmorph fetch-models cpu100 --source SOURCE`` copies them into a local cache, checking
every file against the checksums the package ships (``shipped_models.json``), and
:func:`~divmorph.pretrained.load_pretrained` then finds ``"results/cpu100/teachers/FT"`` (or
``"cpu100/teachers/FT"``) there when the path does not exist where it is run. ``SOURCE`` is a
checkout of the repository, an archive of it (``.tar.gz``, such as a code host's archive of one
commit) or the URL of such an archive.

The cache is ``$DIVMORPH_MODELS``, else ``$XDG_CACHE_HOME/divmorph/models`` (``~/.cache/divmorph/models``);
a run lands in ``<cache>/<run>/`` with its records (``run.json``, ``robot_sets.json``, its evaluation),
so the models load on the robots and env settings they were trained with. Fetching is verified
(SHA-256 of every file), atomic (a staging folder renamed into place when complete) and idempotent.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tarfile
import tempfile
import urllib.error
import urllib.request
from pathlib import Path, PurePosixPath

#: ``{run: {path inside the run folder: sha256}}`` of every shipped file (``tools/shipped_models.py`` writes it).
MANIFEST = Path(__file__).resolve().parent / "shipped_models.json"


class ShippedModelsError(ValueError):
    """A shipped run that cannot be fetched or found (nothing was installed)."""


def shipped_runs() -> dict[str, dict[str, str]]:
    """``{run name: {relative path: sha256}}`` of the runs this package can fetch."""
    return json.loads(MANIFEST.read_text())


def models_cache(cache: str | Path | None = None) -> Path:
    """Where fetched runs live: ``cache``, else ``$DIVMORPH_MODELS``, else the user cache folder."""
    if cache is not None:
        return Path(cache).expanduser()
    if os.environ.get("DIVMORPH_MODELS"):
        return Path(os.environ["DIVMORPH_MODELS"]).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "divmorph" / "models"


def fetch_command(run: str) -> str:
    return f"divmorph fetch-models {run} --source <a checkout of the divmorph repository, or an archive of one>"


def _inside_run(source: str | Path) -> tuple[str, ...] | None:
    """``("cpu100", "teachers", "FT")`` for ``results/cpu100/teachers/FT`` or ``cpu100/teachers/FT``;
    ``None`` when the path names no shipped run."""
    parts = PurePosixPath(Path(source).as_posix()).parts
    parts = parts[1:] if parts[:1] == ("results",) else parts
    return parts if parts and parts[0] in shipped_runs() else None


def shipped_run_of(source: str | Path) -> str | None:
    """The shipped run a path names (``results/cpu100/...`` -> ``cpu100``), else ``None``."""
    parts = _inside_run(source)
    return parts[0] if parts else None


def cached_path(source: str | Path, cache: str | Path | None = None) -> Path | None:
    """The fetched copy of a shipped path (``results/cpu100/teachers/FT`` or ``cpu100/teachers/FT``),
    or ``None`` when ``source`` names no shipped run or that run is not fetched."""
    parts = _inside_run(source)
    folder = models_cache(cache).joinpath(*parts) if parts else None
    return folder if folder is not None and folder.exists() else None


def fetch_models(run: str, source: str | Path, cache: str | Path | None = None, force: bool = False) -> Path:
    """Copy shipped run ``run`` from ``source`` into the cache, verified; returns its folder.

    :param source: a checkout of the repository (``<source>/results/<run>/``), a ``.tar.gz`` archive of
        it (with or without one top folder) or an ``http(s)`` URL of such an archive.
    :param force: fetch again even if the run is already in the cache.
    :raises ShippedModelsError: unknown run, a file missing from the source or differing from its
        checksum, an unreadable archive or a failed download.
    """
    runs = shipped_runs()
    if run not in runs:
        raise ShippedModelsError(f"no shipped run {run!r}; the shipped runs are {sorted(runs)}")
    files = runs[run]
    target = models_cache(cache) / run
    if target.is_dir() and not force:
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{run}-", dir=target.parent))
    try:
        with _SourceFiles(source) as read:
            for relative, digest in files.items():
                content = read(f"results/{run}/{relative}")
                if content is None:
                    raise ShippedModelsError(
                        f"{source} has no results/{run}/{relative}: not a checkout or archive of this project's repository"
                    )
                if hashlib.sha256(content).hexdigest() != digest:
                    raise ShippedModelsError(
                        f"results/{run}/{relative} in {source} differs from the file this package shipped with (SHA-256); "
                        "use a source of the same version"
                    )
                (staging / relative).parent.mkdir(parents=True, exist_ok=True)
                (staging / relative).write_bytes(content)
        if target.exists():
            shutil.rmtree(target)
        staging.rename(target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


class _SourceFiles:
    """``path inside the repository -> bytes or None`` for a checkout, an archive or a URL."""

    def __init__(self, source: str | Path):
        self.source = str(source)
        self._tar: tarfile.TarFile | None = None
        self._download: Path | None = None

    def __enter__(self):
        if self.source.startswith(("http://", "https://")):
            self._download = Path(tempfile.mkstemp(suffix=".tar.gz")[1])
            try:
                with urllib.request.urlopen(self.source, timeout=60) as response, open(self._download, "wb") as out:  # noqa: S310
                    shutil.copyfileobj(response, out)
            except (urllib.error.URLError, OSError, ValueError) as error:
                raise ShippedModelsError(
                    f"could not download {self.source}: {error}. Without a network, give --source a clone of the divmorph "
                    "repository (its results/ folder holds the models) or a .tar.gz archive of one"
                ) from None
            return self._archive(self._download)
        path = Path(self.source).expanduser()
        if path.is_dir():
            return lambda inner: (path / inner).read_bytes() if (path / inner).is_file() else None
        if path.is_file():
            return self._archive(path)
        raise ShippedModelsError(f"no such checkout or archive: {self.source}")

    def _archive(self, path: Path):
        try:
            self._tar = tarfile.open(path)
            members = {m.name: m for m in self._tar.getmembers() if m.isfile()}
        except (tarfile.TarError, OSError, EOFError) as error:
            raise ShippedModelsError(f"{self.source}: not a readable .tar.gz archive ({error})") from None
        tops = {PurePosixPath(name).parts[0] for name in members}
        prefix = f"{tops.pop()}/" if len(tops) == 1 and not any(n.startswith("results/") for n in members) else ""
        tar = self._tar

        def read(inner: str) -> bytes | None:
            member = members.get(prefix + inner)
            extracted = tar.extractfile(member) if member is not None else None
            return extracted.read() if extracted is not None else None

        return read

    def __exit__(self, *exc) -> None:
        if self._tar is not None:
            self._tar.close()
        if self._download is not None:
            self._download.unlink(missing_ok=True)
