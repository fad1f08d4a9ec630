# Session 3, 2026-11-26 15:06-15:21 UTC, one NVIDIA H200 (15 minutes of device time in all).
# Jobs 1-2 sent .gpu/p0 and .gpu/p1 (bash ../shared/gpu/pack.sh, warp-lang 1.19.0, mujoco 4.0.0).
# Job 3 (carry .gpu/p2 .gpu/data; 557 s; its log: log.txt):
STEPS=3 TEACHER_SET="teachers.overrides.batch_size=4096 teachers.overrides.n_epochs=2" bash benchmarks/gpu_session.sh 575
# Job 4, on the still-warm machine (205 s): the same teacher resumed from its 8,089,600-step checkpoint
export PYTHONPATH=/tmp/site:$PWD UNIMAL_DATA=$PWD/.gpu/data PYTHONUNBUFFERED=1 MUJOCO_GL=disable
timeout -k 10 -s INT 200 python3 -m divmorph teachers --profile gpu --out /tmp/gpu-run --train-robots unimals100-train \
  --task FT --no-progress --set teachers.checkpoint_every=1000000 --set teachers.overrides.batch_size=4096 \
  --set teachers.overrides.n_epochs=2
# then its last checkpoint (step 12,134,400; model + optimiser 40 MB, not committed) and the run's logs came back to $OUT
