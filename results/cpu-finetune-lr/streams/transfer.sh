#!/usr/bin/env bash
# The 300k-step transfer race of results/cpu-transfer-300k again, with a smaller learning rate for the
# arms that start from trained weights (`transfer.finetune_overrides`); scratch keeps the rate it was
# calibrated with. No rate is chosen by looking at any evaluation: the sweep is reported whole.
#   divmorph branch --from results/cpu --out results/cpu-finetune-lr/lr-3e-4
#   bash results/cpu-finetune-lr/streams/transfer.sh 3e-4 0 &    # one process per seed, one per core
#   bash results/cpu-finetune-lr/streams/transfer.sh 3e-4 1 &
#   divmorph evaluate --run results/cpu-finetune-lr/lr-3e-4; divmorph report --run results/cpu-finetune-lr/lr-3e-4
# The scratch runs are those of results/cpu-transfer-300k, linked (finetune_overrides do not reach
# scratch, so its settings, seeds and budget are the same): the race compares like with like.
# Resumable: rerun to continue.
set -euo pipefail
lr="$1"; seed="$2"; run="results/cpu-finetune-lr/lr-$lr"
divmorph transfer --run "$run" --no-progress --seeds "$seed" \
  --set transfer.n_timesteps=300000 --set transfer.eval_every=50000 --set transfer.checkpoint_every=50000 \
  --set "transfer.tasks=[PointNav, Exploration]" --set "transfer.arms=[divmorph, closest]" \
  --set "transfer.finetune_overrides={learning_rate: lin_$lr}"
# linked after the runs: the transfer stage is then begun under these settings
for task in PointNav Exploration; do
  mkdir -p "$run/transfer/$task/scratch"
  link="$run/transfer/$task/scratch/seed-$seed"
  [ -e "$link" ] || ln -s "../../../../../cpu-transfer-300k/transfer/$task/scratch/seed-$seed" "$link"
done
