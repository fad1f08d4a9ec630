#!/usr/bin/env bash
# The race's arms from random init (scratch, modumorph) for every job, while the rule for the critics of the
# fine-tuned arms is calibrated on FT (results/critic-start/critic_start.py): these arms have no inherited critic, so
# the rule does not touch them. Same settings as race.sh; its own claims folder. (Used 2026-11-25 before the
# rule was set; kept as the record of what ran.)
set -euo pipefail
RUN=results/cpu-race
CLAIMS="$RUN/streams/claims-random-init"
mkdir -p "$CLAIMS"
for job in Exploration:0 Exploration:1 PointNav:2 Exploration:2 Escape:0 Escape:1 Escape:2; do
  mkdir "$CLAIMS/$job" 2>/dev/null || continue   # another worker has it
  task=${job%%:*}; seed=${job##*:}
  divmorph transfer --run "$RUN" --no-progress --task "$task" --seeds "$seed" \
    --arms scratch,modumorph \
    --set transfer.n_timesteps=300000 --set transfer.eval_every=100000 --set transfer.checkpoint_every=50000 \
    --set transfer.eval_episodes=3 --set "transfer.finetune_overrides={learning_rate: lin_1e-4}" --set transfer.critic_lr_scale=10 \
    --set "transfer.tasks=[PointNav, Exploration, Escape]" --set "transfer.seeds=[0, 1, 2]" \
    --set "transfer.arms=[divmorph, scratch, closest, distilled, modumorph, grl]"
done
