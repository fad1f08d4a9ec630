"""Stable-Baselines3 policies for universal morphology control: MetaMorph, ModuMorph and DivMorph.

This module is the library's front door: it holds what a user imports, as sb3-contrib's top level
holds its algorithms. The policies (:class:`MetaMorphPolicy`, :class:`DivMorphPolicy`,
:class:`ModuMorphPolicy`, :class:`HyperDistillPolicy`); the algorithms (:class:`DevicePPO`, SB3's
PPO with rollouts collected on the device when its env is the batched MuJoCo Warp env, and
:class:`ImitationPPO`, for pure distillation); DAgger distillation (:class:`Teacher`,
:class:`DAggerCallback`, :class:`TeacherMixingVecEnv`); fixed-gate transfer
(:func:`prepare_transfer` with the :class:`UnitSelection` of the tailors the gates select); the
compact actor and its export (:class:`CompactActor`, :func:`export_onnx`, :func:`export_torchscript`,
and :class:`OnnxActor`, which runs the exported file); :func:`load_model` (a saved model with the
observation statistics beside it, as a :class:`NormalizedModel`) and :func:`zoo_hyperparams` (the
shipped rl-zoo settings, ready for ``PPO(...)``). The building blocks (layers, gates, extractors,
presets, the baselines' deployed forms) stay in their own modules (``sb3_divmorph.nn``,
``sb3_divmorph.policies``, ``sb3_divmorph.deploy``, ...).

Importing the package registers ``"MetaMorphPolicy"``, ``"ModuMorphPolicy"``, ``"DivMorphPolicy"``
and ``"HyperDistillPolicy"`` as PPO and A2C policy aliases, so ``PPO("DivMorphPolicy", env)`` and rl-zoo configs with ``policy: DivMorphPolicy``
(with ``--gym-packages sb3_divmorph``) work. They are actor-critic policies, for on-policy algorithms only.
The application built on it (pipeline, command line, run folders) is the package :mod:`divmorph`,
which this one never imports.
"""

from stable_baselines3 import A2C, PPO

from sb3_divmorph.algos.device_ppo import DevicePPO
from sb3_divmorph.algos.distillation import DAggerCallback, ImitationPPO, Teacher, TeacherMixingVecEnv
from sb3_divmorph.algos.finetune import UnitSelection, prepare_transfer
from sb3_divmorph.deploy.compact import CompactActor, export_onnx, export_torchscript
from sb3_divmorph.deploy.onnx_actor import OnnxActor
from sb3_divmorph.policies.hyperdistill import HyperDistillPolicy
from sb3_divmorph.policies.modumorph import ModuMorphPolicy
from sb3_divmorph.policies.morphology_transformer import DivMorphPolicy, MetaMorphPolicy
from sb3_divmorph.saved_model import NormalizedModel, load_model
from sb3_divmorph.zoo import zoo_hyperparams

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
    # policies
    "DivMorphPolicy",
    "HyperDistillPolicy",
    "MetaMorphPolicy",
    "ModuMorphPolicy",
    # algorithms
    "DevicePPO",
    "ImitationPPO",
    # distillation
    "DAggerCallback",
    "Teacher",
    "TeacherMixingVecEnv",
    # transfer
    "UnitSelection",
    "prepare_transfer",
    # deployment
    "CompactActor",
    "OnnxActor",
    "export_onnx",
    "export_torchscript",
    # saved models and settings
    "NormalizedModel",
    "load_model",
    "zoo_hyperparams",
]
