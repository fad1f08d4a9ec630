"""The SB3 policies: MetaMorph and DivMorph (one morphology-aware Transformer, undiverted or
diverted), the baselines ModuMorph and HyperDistill, and GRL's inheritable layers.

May import: :mod:`sb3_divmorph.nn`, :mod:`unimal_envs`. Adding a policy: a module here with an
``ActorCriticPolicy`` subclass built from :mod:`sb3_divmorph.nn`, re-exported below and
registered as an alias in :mod:`sb3_divmorph`.

- :mod:`~sb3_divmorph.policies.morphology_transformer`: ``MetaMorphPolicy``, ``DivMorphPolicy``, presets.
- :mod:`~sb3_divmorph.policies.modumorph`: ``ModuMorphPolicy`` (fixed attention, hypernetwork).
- :mod:`~sb3_divmorph.policies.hyperdistill`: ``HyperDistillPolicy`` (a hypernetwork writing an MLP per robot).
- :mod:`~sb3_divmorph.policies.learngene`: GRL's inheritable layers of a MetaMorph actor.

``sb3_divmorph.policies.MetaMorphPolicy`` is also where saved models look their policy class up.
"""

from sb3_divmorph.policies.hyperdistill import HYPERDISTILL_PRESETS, HyperDistillPolicy
from sb3_divmorph.policies.modumorph import MODUMORPH_PRESETS, ModuMorphPolicy
from sb3_divmorph.policies.morphology_transformer import (
    DIVERSIONS,
    DIVMORPH_PRESETS,
    PRESET_SIZES,
    PRESETS,
    DivMorphPolicy,
    MetaMorphPolicy,
    MorphologyTransformerPolicy,
)

__all__ = [
    "DIVERSIONS",
    "DIVMORPH_PRESETS",
    "HYPERDISTILL_PRESETS",
    "MODUMORPH_PRESETS",
    "PRESETS",
    "PRESET_SIZES",
    "DivMorphPolicy",
    "HyperDistillPolicy",
    "MetaMorphPolicy",
    "ModuMorphPolicy",
    "MorphologyTransformerPolicy",
]
