"""The knowledge-diversion pipeline: teachers -> DAgger distillation -> (GRL) -> transfer -> export -> evaluate -> report.

Each stage is a function of a validated :class:`~divmorph.pipeline.config.Profile` and a run
folder; the ``divmorph`` console script (:mod:`divmorph.cli`) calls the same functions.
Stages skip work whose outputs exist, resume interrupted training from the last checkpoint, and
write their outputs atomically.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from divmorph.profile import Profile

#: What the package exports, by the module that defines it: imported on first use, so that a light
#: module of the pipeline (the profile's keys, the retired rules) loads without torch. The stage
#: functions named like their modules (``distill``, ``evaluate``, ``hyperdistill``, ``report``,
#: ``transfer``) are imported from those modules: ``from divmorph.pipeline.distill import distill``.
_EXPORTS = {
    "ConfigError": "divmorph.pipeline.config",
    "Profile": "divmorph.pipeline.config",
    "load_profile": "divmorph.pipeline.config",
    "export_actor": "divmorph.pipeline.export",
    "export_all": "divmorph.pipeline.export",
    "FIGURES": "divmorph.pipeline.figures",
    "make_figure": "divmorph.pipeline.figures",
    "make_figures": "divmorph.pipeline.figures",
    "GridError": "divmorph.pipeline.grid",
    "make_backend": "divmorph.pipeline.grid",
    "evolve": "divmorph.pipeline.grl",
    "recorded_profile": "divmorph.pipeline.provenance",
    "load_teachers": "divmorph.pipeline.teachers",
    "train_teachers": "divmorph.pipeline.teachers",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


STAGES = ("teachers", "distill", "hyperdistill", "grl", "transfer", "export", "evaluate", "report")


def run_pipeline(profile: Profile, out, progress_bar: bool = True, command: str = "", backend=None) -> str:
    """Run every stage in order (skipping finished ones); returns the markdown summary.

    The HyperDistill baseline runs only when the profile has a ``hyperdistill`` section, GRL's
    evolution only when ``transfer.arms`` has ``grl``.

    :param backend: a :mod:`~divmorph.pipeline.grid` backend for the independent trainings
        (teachers, students, GRL agents, transfer runs); default: local, one after the other.
    """
    from divmorph.pipeline.distill import distill
    from divmorph.pipeline.evaluate import evaluate
    from divmorph.pipeline.export import export_all
    from divmorph.pipeline.grl import evolve
    from divmorph.pipeline.hyperdistill import hyperdistill
    from divmorph.pipeline.report import report
    from divmorph.pipeline.teachers import train_teachers
    from divmorph.pipeline.transfer import transfer

    train_teachers(profile, out, progress_bar=progress_bar, backend=backend)
    distill(profile, out, progress_bar=progress_bar, backend=backend)
    if profile.hyperdistill is not None:
        hyperdistill(profile, out, progress_bar=progress_bar)
    if "grl" in profile.transfer.arm_list():
        evolve(profile, out, backend, progress_bar)
    transfer(profile, out, progress_bar=progress_bar, backend=backend)
    export_all(profile, out)
    evaluate(profile, out, progress_bar=progress_bar)
    return report(profile, out, command)


__all__ = [
    "FIGURES",
    "STAGES",
    "ConfigError",
    "GridError",
    "evolve",
    "make_backend",
    "make_figure",
    "make_figures",
    "Profile",
    "export_actor",
    "export_all",
    "load_profile",
    "load_teachers",
    "recorded_profile",
    "run_pipeline",
    "train_teachers",
]
