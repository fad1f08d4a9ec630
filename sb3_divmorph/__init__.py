"""Stable-Baselines3 policies for universal morphology control: MetaMorph, ModuMorph and DivMorph.

Importing the package registers ``"MetaMorphPolicy"``, ``"ModuMorphPolicy"``, ``"DivMorphPolicy"``
and ``"HyperDistillPolicy"`` as PPO and A2C policy aliases, so ``PPO("DivMorphPolicy", env)`` and rl-zoo configs with ``policy: DivMorphPolicy``
(with ``--gym-packages sb3_divmorph``) work. They are actor-critic policies, for on-policy algorithms only.
:class:`DevicePPO` is SB3's PPO with rollouts collected on the device when its env is the batched
MuJoCo Warp env (``sb3_divmorph.algos.device_ppo``); :func:`load_model` loads a saved model with
the observation statistics beside it. The application built on it (pipeline, command line, run
folders) is the package :mod:`divmorph`, which this one never imports.
"""

from stable_baselines3 import A2C, PPO

from sb3_divmorph.algos.device_ppo import DevicePPO
from sb3_divmorph.deploy.hyperdistill_mlp import HyperDistillMLP
from sb3_divmorph.deploy.modumorph_actor import ModuMorphActor
from sb3_divmorph.nn.distributions import MaskedDiagGaussianDistribution
from sb3_divmorph.nn.extractors import MorphologyTransformerExtractor
from sb3_divmorph.nn.gates import DiversionRouter, GateActivations, MorphologyEncoder, TopKSoftGate
from sb3_divmorph.nn.layers import DenseLinear, Factorization, FactorizedLinear, LinearBuilder
from sb3_divmorph.nn.transformer import MultiHeadSelfAttention, TransformerEncoder, TransformerEncoderLayer
from sb3_divmorph.policies.hyperdistill import HYPERDISTILL_PRESETS, HyperDistillPolicy
from sb3_divmorph.policies.modumorph import MODUMORPH_PRESETS, ModuMorphPolicy
from sb3_divmorph.saved_model import NormalizedModel, load_model
from sb3_divmorph.policies.morphology_transformer import (
    DIVMORPH_PRESETS,
    PRESETS,
    DivMorphPolicy,
    MetaMorphPolicy,
    MorphologyTransformerPolicy,
)

# The policies are SB3 ActorCriticPolicy subclasses: on-policy algorithms (PPO, A2C) take them.
for _algo in (PPO, A2C):
    _algo.policy_aliases.update(
        MetaMorphPolicy=MetaMorphPolicy,
        DivMorphPolicy=DivMorphPolicy,
        ModuMorphPolicy=ModuMorphPolicy,
        HyperDistillPolicy=HyperDistillPolicy,
    )


def _on_policy_only(name: str) -> type:
    """A stand-in registered with the off-policy algorithms, so that ``SAC("DivMorphPolicy", env)``
    says what is wrong instead of SB3's generic "Policy DivMorphPolicy unknown"."""

    class OnPolicyOnly:
        def __init__(self, *args, **kwargs):
            raise TypeError(
                f"{name} is an on-policy actor-critic policy (stochastic actor + state-value critic): use it "
                "with PPO or A2C; off-policy algorithms (SAC, TD3, DDPG, DQN) need Q-function policies"
            )

    OnPolicyOnly.__name__ = OnPolicyOnly.__qualname__ = f"{name}OnPolicyOnly"
    return OnPolicyOnly


def _register_off_policy_guards() -> None:
    from stable_baselines3 import DDPG, DQN, SAC, TD3

    names = ("MetaMorphPolicy", "DivMorphPolicy", "ModuMorphPolicy", "HyperDistillPolicy")
    for algo in (SAC, TD3, DDPG, DQN):
        algo.policy_aliases.update({name: _on_policy_only(name) for name in names if name not in algo.policy_aliases})


_register_off_policy_guards()

__all__ = [
    "DIVMORPH_PRESETS",
    "PRESETS",
    "DenseLinear",
    "DevicePPO",
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
    "NormalizedModel",
    "TopKSoftGate",
    "TransformerEncoder",
    "TransformerEncoderLayer",
    "load_model",
]
