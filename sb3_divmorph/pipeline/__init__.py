"""The knowledge-diversion pipeline: teachers -> DAgger distillation -> transfer -> export -> evaluate -> report.

Each stage is a function of a validated :class:`~sb3_divmorph.pipeline.config.Profile` and a run
folder; the ``divmorph`` console script (:mod:`sb3_divmorph.cli`) calls the same functions.
Stages skip work whose outputs exist, resume interrupted training from the last checkpoint, and
write their outputs atomically.
"""

from sb3_divmorph.pipeline.config import ConfigError, Profile, load_profile
from sb3_divmorph.pipeline.distill import distill
from sb3_divmorph.pipeline.evaluate import evaluate
from sb3_divmorph.pipeline.export import export_actor, export_all
from sb3_divmorph.pipeline.hyperdistill import hyperdistill
from sb3_divmorph.pipeline.report import report
from sb3_divmorph.pipeline.teachers import load_teachers, train_teachers
from sb3_divmorph.pipeline.transfer import transfer

STAGES = ("teachers", "distill", "hyperdistill", "transfer", "export", "evaluate", "report")


def run_pipeline(profile: Profile, out, progress_bar: bool = True, command: str = "") -> str:
    """Run every stage in order (skipping finished ones); returns the markdown summary.

    The HyperDistill baseline runs only when the profile has a ``hyperdistill`` section.
    """
    train_teachers(profile, out, progress_bar=progress_bar)
    distill(profile, out, progress_bar=progress_bar)
    if profile.hyperdistill is not None:
        hyperdistill(profile, out, progress_bar=progress_bar)
    transfer(profile, out, progress_bar=progress_bar)
    export_all(profile, out)
    evaluate(profile, out, progress_bar=progress_bar)
    return report(profile, out, command)


__all__ = [
    "STAGES",
    "ConfigError",
    "Profile",
    "distill",
    "evaluate",
    "export_actor",
    "export_all",
    "hyperdistill",
    "load_profile",
    "load_teachers",
    "report",
    "run_pipeline",
    "train_teachers",
    "transfer",
]
