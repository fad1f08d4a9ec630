"""The knowledge-diversion pipeline: teachers -> DAgger distillation -> (GRL) -> transfer -> export -> evaluate -> report.

Each stage is a function of a validated :class:`~divmorph.pipeline.config.Profile` and a run
folder; the ``divmorph`` console script (:mod:`divmorph.cli`) calls the same functions.
Stages skip work whose outputs exist, resume interrupted training from the last checkpoint, and
write their outputs atomically.
"""

from divmorph.pipeline.config import ConfigError, Profile, load_profile
from divmorph.pipeline.distill import distill
from divmorph.pipeline.evaluate import evaluate
from divmorph.pipeline.export import export_actor, export_all
from divmorph.pipeline.figures import FIGURES, make_figure, make_figures
from divmorph.pipeline.grid import GridError, make_backend
from divmorph.pipeline.grl import evolve
from divmorph.pipeline.hyperdistill import hyperdistill
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.report import report
from divmorph.pipeline.teachers import load_teachers, train_teachers
from divmorph.pipeline.transfer import transfer

STAGES = ("teachers", "distill", "hyperdistill", "grl", "transfer", "export", "evaluate", "report")


def run_pipeline(profile: Profile, out, progress_bar: bool = True, command: str = "", backend=None) -> str:
    """Run every stage in order (skipping finished ones); returns the markdown summary.

    The HyperDistill baseline runs only when the profile has a ``hyperdistill`` section, GRL's
    evolution only when ``transfer.arms`` has ``grl``.

    :param backend: a :mod:`~divmorph.pipeline.grid` backend for the independent trainings
        (teachers, students, GRL agents, transfer runs); default: local, one after the other.
    """
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
    "distill",
    "evaluate",
    "export_actor",
    "export_all",
    "hyperdistill",
    "load_profile",
    "load_teachers",
    "recorded_profile",
    "report",
    "run_pipeline",
    "train_teachers",
    "transfer",
]
