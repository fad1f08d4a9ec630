"""Stable-Baselines3 policies for universal morphology control: MetaMorph, ModuMorph and DivMorph.

Importing the package registers ``"MetaMorphPolicy"``, ``"ModuMorphPolicy"``, ``"DivMorphPolicy"``
and ``"HyperDistillPolicy"`` as PPO policy aliases, so ``PPO("DivMorphPolicy", env)`` and rl-zoo configs with ``policy: DivMorphPolicy``
(with ``--gym-packages sb3_divmorph``) work.
"""

from stable_baselines3 import PPO

from sb3_divmorph.distributions import MaskedDiagGaussianDistribution
from sb3_divmorph.extractors import MorphologyTransformerExtractor
from sb3_divmorph.gates import DiversionRouter, GateActivations, MorphologyEncoder, TopKSoftGate
from sb3_divmorph.hyperdistill import HYPERDISTILL_PRESETS, HyperDistillMLP, HyperDistillPolicy
from sb3_divmorph.layers import DenseLinear, FactorizedLinear, Factorization, LinearBuilder
from sb3_divmorph.modumorph import MODUMORPH_PRESETS, ModuMorphActor, ModuMorphPolicy
from sb3_divmorph.policies import (
    DIVMORPH_PRESETS,
    PRESETS,
    DivMorphPolicy,
    MetaMorphPolicy,
    MorphologyTransformerPolicy,
)
from sb3_divmorph.transformer import MultiHeadSelfAttention, TransformerEncoder, TransformerEncoderLayer

PPO.policy_aliases["MetaMorphPolicy"] = MetaMorphPolicy
PPO.policy_aliases["DivMorphPolicy"] = DivMorphPolicy
PPO.policy_aliases["ModuMorphPolicy"] = ModuMorphPolicy
PPO.policy_aliases["HyperDistillPolicy"] = HyperDistillPolicy

__all__ = [
    "DIVMORPH_PRESETS",
    "PRESETS",
    "DenseLinear",
    "DivMorphPolicy",
    "DiversionRouter",
    "FactorizedLinear",
    "Factorization",
    "GateActivations",
    "HYPERDISTILL_PRESETS",
    "HyperDistillMLP",
    "HyperDistillPolicy",
    "LinearBuilder",
    "MODUMORPH_PRESETS",
    "MaskedDiagGaussianDistribution",
    "MetaMorphPolicy",
    "ModuMorphActor",
    "ModuMorphPolicy",
    "MorphologyEncoder",
    "MorphologyTransformerExtractor",
    "MorphologyTransformerPolicy",
    "MultiHeadSelfAttention",
    "TopKSoftGate",
    "TransformerEncoder",
    "TransformerEncoderLayer",
]
