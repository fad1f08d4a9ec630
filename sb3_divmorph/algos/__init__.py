"""Training algorithms beyond SB3's own: PPO on the device, DAgger distillation, transfer
fine-tuning, MetaMorph's training recipe and HyperDistill's offline fit.

May import: :mod:`sb3_divmorph.nn`, :mod:`sb3_divmorph.policies`, :mod:`unimal_envs`.

- :mod:`~sb3_divmorph.algos.device_ppo`: ``DevicePPO``, SB3's PPO with rollouts on the batched
  MuJoCo Warp env's device.
- :mod:`~sb3_divmorph.algos.distillation`: DAgger, a module per role -- teachers, their labels, the
  beta-mixing VecEnv, the KL loss, the aggregated dataset, ``DAggerCallback``, ``ImitationPPO``.
- :mod:`~sb3_divmorph.algos.finetune`: transfer -- gates fixed, per-unit learning rates, frozen statistics.
- :mod:`~sb3_divmorph.algos.recipe`: MetaMorph's schedule and balanced robot sampling.
- :mod:`~sb3_divmorph.algos.hyperdistill_fit`: HyperDistill's teacher rollouts and offline fit.
"""
