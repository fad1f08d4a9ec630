"""The distilled students the transfer arms start from: each one's policy and how its settings follow
from the profile (a registry, like :mod:`divmorph.pipeline.arms`; the distill stage trains them).

* ``divmorph``: :class:`~sb3_divmorph.policies.DivMorphPolicy` with ``student.policy_kwargs``;
* ``distilled``: a dense :class:`~sb3_divmorph.policies.MetaMorphPolicy` with the teachers'
  ``policy_kwargs`` that reads ``task_embedding`` as one more late-fused input;
* ``no-kdiv-transformer`` / ``no-kdiv-decoder`` / ``no-orthogonality``: the paper's ablations;
* ``deploy-*``: the DivMorph student with a named deployment diversion
  (:data:`~sb3_divmorph.policies.DIVERSIONS`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from stable_baselines3.common.policies import BasePolicy

from sb3_divmorph.nn.extractors import TASK_EMBEDDING
from divmorph.pipeline.config import Profile
from sb3_divmorph.policies.morphology_transformer import DIVERSIONS, PRESETS, DivMorphPolicy, MetaMorphPolicy


@dataclass(frozen=True)
class StudentSpec:
    """A distilled student: its policy and how its ``policy_kwargs`` follow from the profile."""

    name: str
    policy: type[BasePolicy]
    policy_kwargs: Callable[[Profile], dict[str, Any]]
    description: str

    def kwargs(self, profile: Profile) -> dict[str, Any]:
        """The student's ``policy_kwargs`` in ``profile``, its ``student.overrides`` entry applied last."""
        return {**self.policy_kwargs(profile), **profile.student.overrides.get(self.name, {})}


def dense_student_kwargs(profile: Profile) -> dict[str, Any]:
    """The teachers' MetaMorph kwargs, with ``task_embedding`` as one more late-fused input."""
    kwargs = dict(profile.teachers.policy_kwargs)
    preset = PRESETS[kwargs.get("preset", "small")]
    exteroception = dict(kwargs.get("exteroception") or preset["exteroception"])
    exteroception[TASK_EMBEDDING] = [int(kwargs.get("d_model") or preset["d_model"])]
    kwargs["exteroception"] = exteroception
    return kwargs


def _ablated(**switch: bool) -> Callable[[Profile], dict[str, Any]]:
    return lambda profile: {**profile.student.policy_kwargs, **switch}


#: Keys a named diversion decides (the profile's own values would override it, see DivMorphPolicy).
_DIVERSION_KEYS = ("n_morph_tailors", "n_task_tailors", "top_k_morph", "top_k_task", "n_learngenes", "divert_exteroception")


def _diverted(diversion: str) -> Callable[[Profile], dict[str, Any]]:
    def kwargs(profile: Profile) -> dict[str, Any]:
        sizes = {k: v for k, v in profile.student.policy_kwargs.items() if k not in _DIVERSION_KEYS}
        return {**sizes, "diversion": diversion}

    return kwargs


#: Every student the transfer arms start from.
STUDENTS: dict[str, StudentSpec] = {
    spec.name: spec
    for spec in (
        StudentSpec("divmorph", DivMorphPolicy, lambda profile: dict(profile.student.policy_kwargs), "DivMorph student"),
        StudentSpec("distilled", MetaMorphPolicy, dense_student_kwargs, "dense MetaMorph student (reads the task embedding)"),
        StudentSpec(
            "no-kdiv-transformer", DivMorphPolicy, _ablated(divert_transformer=False), "DivMorph student, no diversion in the Transformer"
        ),
        StudentSpec("no-kdiv-decoder", DivMorphPolicy, _ablated(divert_decoder=False), "DivMorph student, no diversion in the decoder"),
        StudentSpec("no-orthogonality", DivMorphPolicy, _ablated(orthogonal=False), "DivMorph student, free square factors"),
        *(
            StudentSpec(name, DivMorphPolicy, _diverted(name), f"DivMorph student with the {name} diversion")
            for name in DIVERSIONS
            if name != "default"
        ),
    )
}
