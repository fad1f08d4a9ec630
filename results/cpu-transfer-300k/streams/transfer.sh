#!/usr/bin/env bash
# The cpu run's transfer race at a budget where scratch can learn: 300k env steps per run (the cpu
# run's own race: 60k), on the teachers and students of results/cpu (linked by `divmorph branch`).
# Tasks: PointNav and Exploration. Escape is left out because at 60k no arm moved on the training
# robots (returns 0-4); the choice looked at training robots only, never the novel ones.
# Arms: DivMorph, scratch, and direct fine-tuning (closest), the paper's headline comparison.
# One process per seed (one per core); resumable: rerun to continue.
#   bash results/cpu-transfer-300k/streams/transfer.sh 0 &
#   bash results/cpu-transfer-300k/streams/transfer.sh 1 &
# Then: divmorph evaluate --run results/cpu-transfer-300k; divmorph report --run results/cpu-transfer-300k
set -euo pipefail
divmorph transfer --run results/cpu-transfer-300k --no-progress --seeds "$1" \
  --set transfer.n_timesteps=300000 --set transfer.eval_every=50000 --set transfer.checkpoint_every=50000 \
  --set "transfer.tasks=[PointNav, Exploration]" --set "transfer.arms=[divmorph, scratch, closest]"
