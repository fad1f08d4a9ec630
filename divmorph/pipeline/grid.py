"""Grids of independent trainings (teachers, students, GRL agents, transfer arms x tasks x seeds), run
in this process or as Ray tasks.

A :class:`Job` names one resumable training by its stage and arguments; :func:`run_job` builds and
runs it in whatever process it lands in, writing into the job's folder exactly as the stage
functions do, so both backends give the same folders, and a finished job (``done.json``) is
skipped by either. A job that fails (an exception, or its process killed) is reported with its
error while the other jobs of the grid go on; rerunning the grid resumes it from its last
checkpoint.

* :class:`LocalBackend` (``--backend local``, the default): one job after the other, in-process.
* :class:`RayBackend` (``--backend ray``): every job a Ray task with ``cpus_per_run`` CPUs and
  ``gpus_per_run`` GPUs, on a local Ray instance started for the grid, or on an existing cluster
  (``--address host:port``, checked to answer within a few seconds first). On a cluster the run
  folder must be on a filesystem every node sees, and the nodes need this package installed.
  Ray is an optional extra: ``pip install ".[ray]"``.
"""

from __future__ import annotations

import importlib
import json
import os
import socket
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from divmorph.pipeline.config import ConfigError, Profile
from divmorph.pipeline.files import atomic_write_json, is_done, read_done

#: ``running.json`` in a job's folder: which process runs it (for the progress display, and to stop it).
RUNNING = "running.json"
BACKENDS = ("local", "ray")


class GridError(RuntimeError):
    """Some jobs of a grid failed (the others finished); the message lists them."""


@dataclass(frozen=True)
class Job:
    """One independent training, named by the importable function that builds it.

    The runner knows jobs, not stages: ``builder`` is ``"module:function"``, called as
    ``function(profile, out, *args, progress_bar=..., **options)`` and returning a resumable
    :class:`~divmorph.pipeline.training.TrainingRun` (a string, so that a Ray worker imports it itself).

    :param builder: e.g. ``"divmorph.pipeline.teachers:teacher_run"``.
    :param args: the builder's arguments after ``profile`` and ``out``.
    :param folder: its run folder.
    :param label: its name in the progress display.
    :param options: keyword arguments of the builder (besides ``progress_bar``).
    """

    builder: str
    args: tuple
    folder: Path
    label: str
    options: dict[str, Any] = field(default_factory=dict)


def job_builder(path: str) -> Callable[..., Any]:
    """The function a job names (``"module:function"``).

    :raises ValueError: not of the form ``module:function``, or no such function.
    """
    module_name, _, function_name = path.partition(":")
    function = getattr(importlib.import_module(module_name), function_name, None) if function_name else None
    if not callable(function):
        raise ValueError(f"job builder {path!r} is not an importable 'module:function'")
    return function


def run_job(profile: Profile, out: Path, job: Job, progress_bar: bool = False) -> dict[str, Any]:
    """Build and run one job here (resuming; a no-op when done); returns its ``done.json``."""
    if not is_done(job.folder):
        build = job_builder(job.builder)
        atomic_write_json(job.folder / RUNNING, {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()})
        build(profile, out, *job.args, progress_bar=progress_bar, **job.options).run()
        (job.folder / RUNNING).unlink(missing_ok=True)
    return read_done(job.folder)


@dataclass
class JobResult:
    job: Job
    status: str  # "done" (trained now), "skipped" (was done), "failed"
    seconds: float = 0.0
    error: str = ""


@dataclass
class GridReport:
    """What happened to every job of a grid."""

    results: list[JobResult] = field(default_factory=list)

    @property
    def failed(self) -> list[JobResult]:
        return [r for r in self.results if r.status == "failed"]

    def summary(self) -> str:
        counts = {s: sum(r.status == s for r in self.results) for s in ("done", "skipped", "failed")}
        lines = [f"[grid] {len(self.results)} runs: {counts['done']} trained, {counts['skipped']} already done, {counts['failed']} failed"]
        lines += [f"[grid]   FAILED {r.job.label} ({r.job.folder}): {r.error}" for r in self.failed]
        return "\n".join(lines)

    def raise_on_failure(self) -> None:
        """:raises GridError: if a job failed (after every other job of the grid has run)."""
        if self.failed:
            raise GridError(self.summary() + "\n(finished runs are kept; rerun the same command to resume the failed ones)")


def _error_text(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[-1] if text else ''}"


class _Display:
    """One line per finished job and a status line of the whole grid (jobs done / running / failed,
    and the steps of the running ones, read from their checkpoints)."""

    def __init__(self, jobs: Sequence[Job], enabled: bool = True):
        self.total = len(jobs)
        self.enabled = enabled
        self.finished = 0
        self.failed = 0
        self.start = time.perf_counter()

    def finish(self, result: JobResult) -> None:
        self.finished += 1
        self.failed += result.status == "failed"
        what = f"failed: {result.error}" if result.status == "failed" else f"{result.status} in {result.seconds:.0f} s"
        print(f"[grid {self.finished}/{self.total}] {result.job.label}: {what}", flush=True)

    def status(self, pending: Sequence[tuple[Job, float]]) -> None:
        """:param pending: submitted jobs not finished yet, with their submission times."""
        if not self.enabled:
            return
        running, queued = [], 0
        for job, submitted in pending:
            try:
                started = json.loads((job.folder / RUNNING).read_text())["started"] >= submitted - 1
            except (OSError, ValueError, KeyError):
                started = False
            if not started:
                queued += 1
                continue
            try:
                steps = json.loads((job.folder / "checkpoints" / "latest.json").read_text())["num_timesteps"]
            except (OSError, ValueError, KeyError):
                steps = 0
            running.append(f"{job.label} @ {steps} steps")
        print(
            f"[grid] {self.finished}/{self.total} finished ({self.failed} failed), {len(running)} running "
            f"[{'; '.join(running)}], {queued} queued, {time.perf_counter() - self.start:.0f} s",
            flush=True,
        )


class LocalBackend:
    """Runs the jobs one after the other in this process (today's behaviour)."""

    name = "local"

    def run(self, profile: Profile, out: Path, jobs: Sequence[Job], display: _Display, progress_bar: bool) -> list[JobResult]:
        results = []
        for job in jobs:
            start = time.perf_counter()
            try:
                run_job(profile, out, job, progress_bar)
                result = JobResult(job, "done", time.perf_counter() - start)
            except Exception as error:  # noqa: BLE001 - reported, the other jobs go on
                traceback.print_exc()
                result = JobResult(job, "failed", time.perf_counter() - start, _error_text(error))
            display.finish(result)
            results.append(result)
        return results


def check_address(address: str, timeout: float = 5.0) -> None:
    """Fail fast, with a clear message, when a Ray address does not accept connections.

    :raises ConfigError: malformed address, or nothing answers at it within ``timeout`` seconds.
    """
    if address in ("auto", "local"):
        return
    bare = address.split("://", 1)[-1]
    host, _, port = bare.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"Ray address {address!r} is not host:port (or ray://host:port, or 'auto')")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as error:
        raise ConfigError(
            f"Ray address {address!r} does not answer ({error or type(error).__name__}); "
            "start the cluster (`ray start --head`) or leave --address out for a local Ray"
        ) from None


def _remote_job(profile: Profile, out: Path, job: Job, threads: int) -> dict[str, Any]:
    import torch as th

    th.set_num_threads(max(1, threads))
    return run_job(profile, out, job, progress_bar=False)


class RayBackend:
    """Runs the jobs as Ray tasks (see the module docstring).

    :param address: an existing cluster (``host:port``, ``ray://host:port`` or ``auto``); ``None``:
        start a local Ray instance for the grid.
    :param cpus_per_run: CPUs Ray reserves for each job (also its torch threads).
    :param gpus_per_run: GPUs (fractions allowed) Ray reserves for each job.
    :param num_cpus: CPUs of the local instance (default: all of this machine's).
    :param status_every: seconds between status lines of the progress display.
    """

    name = "ray"

    def __init__(
        self,
        address: str | None = None,
        cpus_per_run: float = 1,
        gpus_per_run: float = 0,
        num_cpus: int | None = None,
        status_every: float = 30.0,
    ):
        if cpus_per_run <= 0 or gpus_per_run < 0:
            raise ConfigError(f"--cpus-per-run must be > 0 and --gpus-per-run >= 0, got {cpus_per_run} and {gpus_per_run}")
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ConfigError('the Ray backend needs Ray: pip install ".[ray]"') from None
        if address is not None:
            check_address(address)
        self.address = address
        self.cpus_per_run = cpus_per_run
        self.gpus_per_run = gpus_per_run
        self.num_cpus = num_cpus
        self.status_every = status_every

    def _init(self) -> None:
        import atexit

        import ray

        if ray.is_initialized():
            return
        package_root = str(Path(__file__).resolve().parents[2])
        env = {key: os.environ[key] for key in ("MUJOCO_GL", "HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE") if key in os.environ}
        # workers import this checkout (not another install of the package)
        env["PYTHONPATH"] = os.pathsep.join([package_root, *filter(None, [os.environ.get("PYTHONPATH")])])
        kwargs: dict[str, Any] = dict(include_dashboard=False, log_to_driver=False, runtime_env={"env_vars": env})
        if self.address is None:
            kwargs["num_cpus"] = self.num_cpus or os.cpu_count() or 1
        else:
            kwargs["address"] = self.address
        ray.init(**kwargs)
        # one Ray for every grid of this command (a pipeline runs several); shut down when the command ends
        atexit.register(ray.shutdown)

    def run(self, profile: Profile, out: Path, jobs: Sequence[Job], display: _Display, progress_bar: bool) -> list[JobResult]:
        import ray

        self._init()
        remote = ray.remote(num_cpus=self.cpus_per_run, num_gpus=self.gpus_per_run, max_retries=0)(_remote_job)
        threads = max(1, int(self.cpus_per_run))
        pending = {remote.remote(profile, Path(out).resolve(), job, threads): (job, time.time()) for job in jobs}
        results = []
        last_status = time.perf_counter()
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=min(self.status_every, 5.0))
            for ref in ready:
                job, submitted = pending.pop(ref)
                try:
                    ray.get(ref)
                    result = JobResult(job, "done", time.time() - submitted)
                except Exception as error:  # noqa: BLE001 - a task error or a killed worker: reported, others go on
                    result = JobResult(job, "failed", time.time() - submitted, _error_text(error))
                display.finish(result)
                results.append(result)
            if time.perf_counter() - last_status >= self.status_every:
                display.status(list(pending.values()))
                last_status = time.perf_counter()
        return results


def make_backend(
    name: str = "local", address: str | None = None, cpus_per_run: float = 1, gpus_per_run: float = 0, num_cpus: int | None = None
):
    """The backend called ``name`` (``local`` or ``ray``; the other arguments: see :class:`RayBackend`).

    :raises ConfigError: unknown backend, Ray options without ``ray``, Ray missing or not answering.
    """
    if name not in BACKENDS:
        raise ConfigError(f"unknown backend {name!r}; choose from {list(BACKENDS)}")
    if name == "local":
        if address is not None:
            raise ConfigError("--address needs --backend ray")
        return LocalBackend()
    if num_cpus is not None and address is not None:
        raise ConfigError("--ray-cpus sizes a local Ray instance; a cluster given with --address has its own")
    return RayBackend(address, cpus_per_run, gpus_per_run, num_cpus)


def run_grid(profile: Profile, out: Path, jobs: Sequence[Job], backend=None, progress_bar: bool = True) -> GridReport:
    """Run every job not yet done on ``backend`` (default: local); failures are collected, not raised.

    :return: the :class:`GridReport`; call :meth:`GridReport.raise_on_failure` to stop on failures.
    """
    backend = backend or LocalBackend()
    todo = [job for job in jobs if not is_done(job.folder)]
    report = GridReport([JobResult(job, "skipped") for job in jobs if is_done(job.folder)])
    if todo:
        if len(jobs) > 1:
            print(
                f"[grid] {len(todo)} of {len(jobs)} runs to train on the {backend.name} backend ({len(jobs) - len(todo)} already done)",
                flush=True,
            )
        display = _Display(todo, enabled=True)
        report.results += backend.run(profile, Path(out), todo, display, progress_bar and backend.name == "local")
    if len(jobs) > 1 or report.failed:
        print(report.summary(), file=sys.stderr if report.failed else sys.stdout, flush=True)
    return report
