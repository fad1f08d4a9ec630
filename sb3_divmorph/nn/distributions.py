"""Diagonal Gaussian over a padded action vector, counting real action slots only."""

from __future__ import annotations

from typing import TypeVar

import torch as th
from stable_baselines3.common.distributions import DiagGaussianDistribution
from torch.distributions import Normal

SelfMaskedDiagGaussian = TypeVar("SelfMaskedDiagGaussian", bound="MaskedDiagGaussianDistribution")


class MaskedDiagGaussianDistribution(DiagGaussianDistribution):
    """Diagonal Gaussian whose log-probability and entropy sum over real action slots only.

    A robot with fewer hinges than the padded action vector has slots the env ignores; their
    samples must not enter the PPO ratio or the entropy bonus (MetaMorph zeroes them the same way).
    Padded means are set to 0, so deterministic actions are clean there too.

    :param action_dim: size of the padded action vector.
    """

    def __init__(self, action_dim: int):
        super().__init__(action_dim)
        self.real: th.Tensor | None = None

    def proba_distribution(
        self: SelfMaskedDiagGaussian,
        mean_actions: th.Tensor,
        log_std: th.Tensor,
        action_padding_mask: th.Tensor | None = None,
    ) -> SelfMaskedDiagGaussian:
        """
        :param mean_actions: (B, A) means.
        :param log_std: (A,) or (B, A) log standard deviations.
        :param action_padding_mask: (B, A), True or 1.0 = padded slot; ``None`` = no padding.
        """
        if action_padding_mask is None:
            self.real = None
        else:
            padded = action_padding_mask if action_padding_mask.dtype == th.bool else action_padding_mask > 0.5
            self.real = ~padded
            zero = th.zeros((), dtype=mean_actions.dtype, device=mean_actions.device)
            mean_actions = th.where(self.real, mean_actions, zero)
        # Argument checks (a finite mean, a positive std) cost a device sync each; a rollout step (no autograd)
        # skips them -- a non-finite action is refused by the env, which names it -- and training passes keep them.
        validate = None if th.is_grad_enabled() else False
        self.distribution = Normal(mean_actions, th.ones_like(mean_actions) * log_std.exp(), validate_args=validate)
        return self

    def _masked_sum(self, values: th.Tensor) -> th.Tensor:
        if self.real is not None:
            # where, not multiply: a padded slot holding inf/nan must still contribute exactly 0
            values = th.where(self.real, values, th.zeros((), dtype=values.dtype, device=values.device))
        return values.sum(dim=-1)

    def log_prob(self, actions: th.Tensor) -> th.Tensor:
        return self._masked_sum(self.distribution.log_prob(actions))

    def entropy(self) -> th.Tensor:
        return self._masked_sum(self.distribution.entropy())

    def actions_from_params(
        self,
        mean_actions: th.Tensor,
        log_std: th.Tensor,
        deterministic: bool = False,
        action_padding_mask: th.Tensor | None = None,
    ) -> th.Tensor:
        self.proba_distribution(mean_actions, log_std, action_padding_mask)
        return self.get_actions(deterministic=deterministic)

    def log_prob_from_params(
        self, mean_actions: th.Tensor, log_std: th.Tensor, action_padding_mask: th.Tensor | None = None
    ) -> tuple[th.Tensor, th.Tensor]:
        actions = self.actions_from_params(mean_actions, log_std, action_padding_mask=action_padding_mask)
        return actions, self.log_prob(actions)
