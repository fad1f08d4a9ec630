#!/usr/bin/env bash
# The fair transfer race (issue 26) on the cpu run's teachers and students (linked by `divmorph branch`):
# 3 novel tasks x the 6 main arms x 3 seeds, 300k env steps per run, evaluated every 100k steps on the
# 10 training and 10 novel robots with 3 deterministic episodes per robot.
# One rule for every arm that starts from trained weights (closest, distilled, divmorph, grl): a
# fine-tuning learning rate lin_1e-4, chosen on the training task FT (results/first_update_kl.md: the
# rate at which every such start's first PPO update is the size of scratch's first update at lin_1e-3);
# Their critics learn at 10x that rate (transfer.critic_lr_scale=10: lin_1e-3, scratch's rate), chosen on FT
# (results/critic-start: the critic that explains the returns; a first pass with the critics at lin_1e-4 is in
# superseded/20261125-201314). Adam eps 1e-10 and frozen inherited observation statistics for all (the profile
# defaults). Arms from random init (scratch, modumorph) keep the teachers' lin_1e-3 (their runs from before the
# critic rule stand: it does not touch them).
# Jobs (task, seed) are claimed from a shared queue, so any number of workers can run; one per core:
#   bash results/cpu-race/streams/race.sh &
#   bash results/cpu-race/streams/race.sh &
# Resumable: rerun to continue (finished runs are skipped, unfinished ones resume from their checkpoint).
# Then: divmorph evaluate --run results/cpu-race; divmorph report --run results/cpu-race
set -euo pipefail
RUN=results/cpu-race
CLAIMS="$RUN/streams/claims"
mkdir -p "$CLAIMS"
for job in PointNav:0 PointNav:1 Exploration:0 Exploration:1 PointNav:2 Exploration:2 Escape:0 Escape:1 Escape:2; do
  mkdir "$CLAIMS/$job" 2>/dev/null || continue   # another worker has it
  task=${job%%:*}; seed=${job##*:}
  divmorph transfer --run "$RUN" --no-progress --task "$task" --seeds "$seed" \
    --arms divmorph,scratch,closest,distilled,modumorph,grl \
    --set transfer.n_timesteps=300000 --set transfer.eval_every=100000 --set transfer.checkpoint_every=50000 \
    --set transfer.eval_episodes=3 --set "transfer.finetune_overrides={learning_rate: lin_1e-4}" --set transfer.critic_lr_scale=10 \
    --set "transfer.tasks=[PointNav, Exploration, Escape]" --set "transfer.seeds=[0, 1, 2]" \
    --set "transfer.arms=[divmorph, scratch, closest, distilled, modumorph, grl]"
done
