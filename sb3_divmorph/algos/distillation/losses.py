"""The distillation loss: ``KL(pi_teacher || pi_student)`` between diagonal Gaussians over the real action slots."""

from __future__ import annotations

import torch as th
from torch.distributions import Normal, kl_divergence


def gaussian_kl(
    teacher_mean: th.Tensor, teacher_std: th.Tensor, student_mean: th.Tensor, student_std: th.Tensor, real: th.Tensor
) -> th.Tensor:
    """``KL(N_teacher || N_student)`` per sample, summed over real action slots: (B, A) x4, (B, A) bool -> (B,)."""
    per_slot = kl_divergence(Normal(teacher_mean, teacher_std), Normal(student_mean, student_std))
    return th.where(real, per_slot, th.zeros((), dtype=per_slot.dtype, device=per_slot.device)).sum(-1)
