#!/usr/bin/env bash
# Videos of the cpu run (headless): the FT teacher on its best training robot, the DivMorph student on
# FT on its best training robot and on the novel robot (never trained on) where its evaluation
# return is highest: chosen for
# display, after the fact; the evaluation table has every robot.
set -euo pipefail
RUN=results/cpu; V=$RUN/videos; mkdir -p $V
pick() {  # robot with the best deterministic return of model $1 on task $2, split $3 (evaluate/returns.csv)
  python - "$@" <<'PY'
import sys
from divmorph.pipeline.report import read_returns
model, task, split = sys.argv[1:4]
rows = [r for r in read_returns("results/cpu/evaluate/returns.csv") if (r["model"], r["task"], r["split"]) == (model, task, split)]  # (or .csv.gz)
print(max(rows, key=lambda r: float(r["return"]))["morphology"])
PY
}
TEACHER_ROBOT=$(pick teacher FT train)
STUDENT_ROBOT=$(pick student FT novel)
STUDENT_TRAIN_ROBOT=$(pick student FT train)
for ext in mp4 gif; do
  size=$([ $ext = gif ] && echo "--width 256 --height 192 --steps 500" || echo "--width 480 --height 360")
  divmorph record $RUN/teachers/FT --morphologies unimals100-train --robot "$TEACHER_ROBOT" $size --out $V/teacher-FT-$TEACHER_ROBOT.$ext --no-progress
  divmorph record $RUN/student --task FT --morphologies unimals100-train --robot "$STUDENT_ROBOT" $size --out $V/student-FT-novel-$STUDENT_ROBOT.$ext --no-progress
done
divmorph record $RUN/student --task FT --morphologies unimals100-train --robot "$STUDENT_TRAIN_ROBOT" --width 256 --height 192 --steps 500 \
  --out $V/student-FT-train-$STUDENT_TRAIN_ROBOT.gif --no-progress
# the one video in the repository (the others are not shipped, to keep the tracked files small): 3 s of the FT teacher, small
divmorph record $RUN/teachers/FT --morphologies unimals100-train --robot "$TEACHER_ROBOT" --width 192 --height 144 --steps 150 \
  --out $V/teacher-FT-$TEACHER_ROBOT-3s.gif --no-progress
