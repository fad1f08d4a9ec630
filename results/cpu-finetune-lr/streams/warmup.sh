#!/usr/bin/env bash
# The 300k-step race of results/cpu-transfer-300k again (the profile's learning rate, lin_1e-3), with a
# critic-only warm-up of the first 20k env steps (7% of the budget, fixed beforehand, not tuned) for the
# arms that start from trained weights (`transfer.critic_warmup`): none of them arrives with a critic for
# the novel task, and the distilled students' critics were never trained.
#   divmorph branch --from results/cpu --out results/cpu-finetune-lr/warmup-20k
#   bash results/cpu-finetune-lr/streams/warmup.sh 0; bash results/cpu-finetune-lr/streams/warmup.sh 1
#   divmorph evaluate --run results/cpu-finetune-lr/warmup-20k; divmorph report --run results/cpu-finetune-lr/warmup-20k
# Scratch is linked from results/cpu-transfer-300k as in transfer.sh (the warm-up does not reach it).
set -euo pipefail
seed="$1"; run="results/cpu-finetune-lr/warmup-20k"
divmorph transfer --run "$run" --no-progress --seeds "$seed" \
  --set transfer.n_timesteps=300000 --set transfer.eval_every=50000 --set transfer.checkpoint_every=50000 \
  --set "transfer.tasks=[PointNav, Exploration]" --set "transfer.arms=[divmorph, closest]" \
  --set transfer.critic_warmup=20000
# linked after the runs: the transfer stage is then begun under these settings
for task in PointNav Exploration; do
  mkdir -p "$run/transfer/$task/scratch"
  link="$run/transfer/$task/scratch/seed-$seed"
  [ -e "$link" ] || ln -s "../../../../../cpu-transfer-300k/transfer/$task/scratch/seed-$seed" "$link"
done
