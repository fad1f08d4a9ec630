"""Stable-Baselines3 policies for universal morphology control: MetaMorph, ModuMorph and DivMorph.

Importing the package registers ``"MetaMorphPolicy"``, ``"ModuMorphPolicy"``, ``"DivMorphPolicy"``
and ``"HyperDistillPolicy"`` as PPO and A2C policy aliases, so ``PPO("DivMorphPolicy", env)`` and rl-zoo configs with ``policy: DivMorphPolicy``
(with ``--gym-packages sb3_divmorph``) work. They are actor-critic policies, for on-policy algorithms only.
:class:`DevicePPO` is SB3's PPO with rollouts collected on the device when its env is the batched
MuJoCo Warp env (``sb3_divmorph.algos.device_ppo``).
"""

import importlib
import importlib.abc
import importlib.util
import sys

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

#: Module paths from before the package was organised by concept (issue 45) -> where the code is now.
#: Saved models name their policy class by module (``sb3_divmorph.hyperdistill.HyperDistillPolicy``),
#: and scripts import the old paths: both keep working, without a module left behind for each.
MOVED_MODULES = {
    **{
        f"sb3_divmorph.{name}": f"sb3_divmorph.nn.{name}"
        for name in ("layers", "gates", "transformer", "decoders", "extractors", "distributions")
    },
    **{f"sb3_divmorph.{name}": f"sb3_divmorph.policies.{name}" for name in ("modumorph", "hyperdistill", "learngene")},
    **{f"sb3_divmorph.{name}": f"sb3_divmorph.algos.{name}" for name in ("device_ppo", "distillation", "finetune", "recipe")},
    **{f"sb3_divmorph.{name}": f"sb3_divmorph.deploy.{name}" for name in ("compact", "deployment", "onnx_actor")},
}


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Resolves an old module path (:data:`MOVED_MODULES`) to the module that lives there now."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in MOVED_MODULES:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        # the module object itself: the import system files it under the old name as well
        return importlib.import_module(MOVED_MODULES[spec.name])

    def exec_module(self, module):
        pass  # already executed under its new name


sys.meta_path.append(_MovedModuleFinder())

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
    "TopKSoftGate",
    "TransformerEncoder",
    "TransformerEncoderLayer",
]
