#!/usr/bin/env bash
# Videos of the cpu100 run (headless, after its evaluation): the FT teacher and the DivMorph student on
# the same novel robot (never trained on, zero-shot) -- the novel robot where the teacher's
# deterministic FT return is highest, chosen for display after the fact (the evaluation table has
# every robot) -- and the teacher on its best training robot. Small 3 s GIFs ship; the MP4s do not.
set -euo pipefail
RUN=results/cpu100; V=$RUN/videos; mkdir -p $V
pick() {  # robot with the best deterministic return of model $1 on task $2, split $3 (evaluate/returns.csv)
  python - "$@" <<'PY'
import sys
from divmorph.pipeline.report import read_returns  # (returns.csv, or returns.csv.gz once packed)
model, task, split = sys.argv[1:4]
rows = [r for r in read_returns("results/cpu100/evaluate/returns.csv") if (r["model"], r["task"], r["split"]) == (model, task, split)]
print(max(rows, key=lambda r: float(r["return"]))["morphology"])
PY
}
NOVEL=$(pick teacher FT novel)
TRAIN=$(pick teacher FT train)
for who in teacher student; do
  source=$([ $who = teacher ] && echo $RUN/teachers/FT || echo "$RUN/student --task FT")
  # shellcheck disable=SC2086
  divmorph record $source --morphologies novel --robot "$NOVEL" --width 480 --height 360 --out $V/$who-FT-novel-$NOVEL.mp4 --no-progress
  # shellcheck disable=SC2086
  divmorph record $source --morphologies novel --robot "$NOVEL" --width 192 --height 144 --steps 150 --out $V/$who-FT-novel-$NOVEL-3s.gif --no-progress
done
divmorph record $RUN/teachers/FT --morphologies unimals100-train --robot "$TRAIN" --width 480 --height 360 --out $V/teacher-FT-train-$TRAIN.mp4 --no-progress
divmorph record $RUN/teachers/FT --morphologies unimals100-train --robot "$TRAIN" --width 192 --height 144 --steps 150 --out $V/teacher-FT-train-$TRAIN-3s.gif --no-progress
