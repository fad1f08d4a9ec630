"""The transfer arms: the ways a researcher could start on a novel task, raced on one budget.

Every arm trains with PPO on the novel task, on the profile's training robots, with the novel
task's rl-zoo settings (``transfer.overrides``; arms that start from trained weights take
``transfer.finetune_overrides`` on top, and a critic-only warm-up of ``transfer.critic_warmup``
env steps), for ``transfer.n_timesteps`` steps, and is evaluated the
same way (:mod:`divmorph.pipeline.curves`). They differ in where they start:

========================  ==========================================================================
arm                       start
========================  ==========================================================================
``divmorph``              the distilled DivMorph student; gates fixed, selected tailors trained,
                          learngenes ``learngene_lr_scale`` times slower
``scratch``               MetaMorph, random init
``closest``               (MetaMorph→) the teacher of the most similar training task, fully fine-tuned
``distilled``             (MetaMorph⚗) a dense MetaMorph student distilled from all teachers (it
                          reads the task embedding through one more late-fused encoder), fully
                          fine-tuned
``modumorph``             ModuMorph, random init
``grl``                   MetaMorph with GRL's best evolved learngene (whole layers) inherited
``divmorph-finetuned``    the distilled DivMorph student fine-tuned like MetaMorph⚗: every weight, its
                          router (so its gates) included, at the fine-tuning rate. It separates what
                          DivMorph's transfer rule does from what its diverted weights do
``no-kdiv-transformer``   a DivMorph student distilled without diversion in the Transformer,
                          transferred the DivMorph way
``no-kdiv-decoder``       likewise without diversion in the decoder
``no-orthogonality``      likewise with free (not Cayley-orthogonal) square factors
========================  ==========================================================================
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Arm:
    """One transfer arm.

    :param name: the name on the command line and in folders.
    :param label: the name in plots and tables.
    :param student: the distilled student it starts from (a key of
        :data:`divmorph.pipeline.students.STUDENTS`), or ``None``.
    :param divmorph_transfer: transferred the DivMorph way (fixed gates, per-unit learning rates).
    :param ablation: one of the paper's ablations (plotted in the ablation figure).
    :param gated: starts from a DivMorph student, whose router reads the task (so
        ``transfer.task_gates`` decides the instruction it is told).
    :param control: a diagnostic arm, not one of the paper's (in none of its figures).
    """

    name: str
    label: str
    student: str | None = None
    divmorph_transfer: bool = False
    ablation: bool = False
    gated: bool = False
    control: bool = False


_ARMS = (
    Arm("divmorph", "DivMorph", student="divmorph", divmorph_transfer=True, gated=True),
    Arm("scratch", "MetaMorph (scratch)"),
    Arm("closest", "MetaMorph→ (closest task)"),
    Arm("distilled", "MetaMorph⚗ (distilled)", student="distilled"),
    Arm("modumorph", "ModuMorph (scratch)"),
    Arm("grl", "GRL (evolved learngene)"),
    Arm("divmorph-finetuned", "DivMorph (fully fine-tuned)", student="divmorph", gated=True, control=True),
    Arm(
        "no-kdiv-transformer",
        "DivMorph w/o KDiv (Transformer)",
        student="no-kdiv-transformer",
        divmorph_transfer=True,
        ablation=True,
        gated=True,
    ),
    Arm("no-kdiv-decoder", "DivMorph w/o KDiv (decoder)", student="no-kdiv-decoder", divmorph_transfer=True, ablation=True, gated=True),
    Arm("no-orthogonality", "DivMorph w/o orthogonality", student="no-orthogonality", divmorph_transfer=True, ablation=True, gated=True),
)

#: Every arm by name, in the order of plots and tables.
ARMS: dict[str, Arm] = {arm.name: arm for arm in _ARMS}

#: Arms of the transfer figures (Figs 3-4: the paper's, no control arm); the ablation figure (Fig 6) shows ``divmorph`` and the ablations.
MAIN_ARMS = tuple(name for name, arm in ARMS.items() if not (arm.ablation or arm.control))
ABLATION_ARMS = ("divmorph", *(name for name, arm in ARMS.items() if arm.ablation))


def students_for(arms: list[str]) -> list[str]:
    """The distilled students these arms start from, in order, each once."""
    students: list[str] = []
    for name in arms:
        student = ARMS[name].student
        if student is not None and student not in students:
            students.append(student)
    return students
