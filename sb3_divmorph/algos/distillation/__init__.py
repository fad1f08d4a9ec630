"""DAgger-style policy distillation: per-task teachers label the states a student visits.

DivMorph trains its knowledge-diverted student by distillation from one MetaMorph teacher per
training task. The pieces, usable with any SB3 on-policy algorithm:

* :class:`Teacher`: a trained policy with the observation normalisation it was trained under.
* :class:`DAggerCallback`: records the raw observations of every rollout, has each state labelled
  by the teacher of its own task (``task_index`` observation), aggregates them in a bounded
  dataset, and fits the student to the teachers' action distributions after each rollout.
* :class:`TeacherMixingVecEnv`: executes the teacher's action instead of the student's with
  probability ``beta`` (DAgger's beta-mixture), annealed by the callback.
* :class:`ImitationPPO`: PPO with its own update switched off, for pure distillation; with plain
  :class:`~stable_baselines3.PPO` the callback runs alongside the PPO loss.

**Loss.** For each state, ``KL(pi_teacher || pi_student)`` between the two diagonal Gaussians,
summed over the robot's real action slots (padded slots carry no action) and averaged over the
batch. With MetaMorph's fixed, equal standard deviations this is the squared error of the means
divided by ``2 sigma^2``; with a learnt student std it also matches the teacher's spread.

**On the device.** With :class:`ImitationPPO` (a :class:`~sb3_divmorph.algos.device_ppo.DevicePPO`)
on the batched MuJoCo Warp env, nothing of DAgger leaves the device in the rollout loop: the raw
states are the env's tensors (``DevicePPO.last_raw_obs``), every teacher labels them with its
statistics applied in torch (:func:`teacher_labels_on_device`), the aggregated dataset is stored as
tensors, and beta's teacher actions are mixed in by DevicePPO (``executed_actions``) instead of a
:class:`TeacherMixingVecEnv` (which would send every step through the host). The result is the
VecEnv path's: the same states, labels, dataset and update (``tests/test_device_ppo.py``).

**Modules**, one role each (every name below is importable from this package too):

* :mod:`~sb3_divmorph.algos.distillation.teacher`: :class:`Teacher`;
  :mod:`~sb3_divmorph.algos.distillation.normalizer`: :func:`load_normalizer`;
  :mod:`~sb3_divmorph.algos.distillation.space_checks`: :class:`SpaceMismatchError`, :func:`check_spaces`.
* :mod:`~sb3_divmorph.algos.distillation.labels`: :func:`teacher_labels`, :func:`teacher_labels_on_device`,
  :func:`teacher_values`; :mod:`~sb3_divmorph.algos.distillation.observations`: raw observation batches
  (``ObsDict``, ``TASK_INDEX``, :func:`index_obs`).
* :mod:`~sb3_divmorph.algos.distillation.mixing`: :class:`TeacherMixingVecEnv`.
* :mod:`~sb3_divmorph.algos.distillation.losses`: :func:`gaussian_kl`.
* :mod:`~sb3_divmorph.algos.distillation.dataset`: :class:`DistillationDataset`.
* :mod:`~sb3_divmorph.algos.distillation.callback`: :class:`DAggerCallback`.
* :mod:`~sb3_divmorph.algos.distillation.imitation_ppo`: :class:`ImitationPPO`.
"""

from sb3_divmorph.algos.distillation.callback import DATASET_FILE, DAggerCallback, STATE_FILE
from sb3_divmorph.algos.distillation.dataset import DistillationDataset
from sb3_divmorph.algos.distillation.imitation_ppo import ImitationPPO
from sb3_divmorph.algos.distillation.labels import teacher_for, teacher_labels, teacher_labels_on_device, teacher_values
from sb3_divmorph.algos.distillation.losses import gaussian_kl
from sb3_divmorph.algos.distillation.mixing import TeacherMixingVecEnv
from sb3_divmorph.algos.distillation.normalizer import load_normalizer
from sb3_divmorph.algos.distillation.observations import ObsDict, TASK_INDEX, index_obs, task_indices, to_numpy
from sb3_divmorph.algos.distillation.space_checks import SpaceMismatchError, check_spaces
from sb3_divmorph.algos.distillation.teacher import Teacher

__all__ = [
    "DATASET_FILE",
    "DAggerCallback",
    "DistillationDataset",
    "ImitationPPO",
    "ObsDict",
    "STATE_FILE",
    "SpaceMismatchError",
    "TASK_INDEX",
    "Teacher",
    "TeacherMixingVecEnv",
    "check_spaces",
    "gaussian_kl",
    "index_obs",
    "load_normalizer",
    "task_indices",
    "teacher_for",
    "teacher_labels",
    "teacher_labels_on_device",
    "teacher_values",
    "to_numpy",
]
