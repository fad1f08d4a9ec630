#!/usr/bin/env bash
# The GPU work order of ../shared/gpu/README.md as one job, for a machine lent for minutes.
#
# Runs ON the GPU machine, in the project's root, after the parts .gpu/p0 and .gpu/p1 were copied to
# /tmp/gpu by the jobs before (the README's table); this job carries .gpu/p2 and .gpu/data (the
# official robots: `UNIMAL_DATA=.gpu/data python -m unimal_envs.morphology fetch --source
# ../shared/unimals_100 --sets train test`; the `gpu` profile's novel split is the held-out set, which
# a teacher does not need but an evaluation does):
#
#     bash benchmarks/gpu_session.sh SECONDS
#
# SECONDS is the time this job may use in all: each step gets a share of what is left (SIGINT at its
# end, SIGKILL 20 s later), and whatever a step printed or wrote comes back even when its share runs
# out (the log, and one archive of the result files, both in $OUT; an interrupted benchmark writes the
# rows it measured). In order of the work order:
#   1. env steps/s of the batched backend on CUDA, FT and VT, the 100 official robots, 32-512 worlds
#      per robot, beside the single C env on the same machine (benchmarks/batched_throughput.py);
#   2. end-to-end PPO samples/s on 100 robots with the small and the paper-size MetaMorph policy
#      (SB3's VecEnv path and DevicePPO), with the rollout/update split;
#   3. a paper-size FT teacher on the 100 robots (the `gpu` profile) for the time left (over a minute);
#   4. (STEPS=4) the transfer race of issue 42 on the device from the cpu100 models (RACE_* below, at step 4).
# WORLDS="128 512" picks step 1's worlds per robot; PPO_SHARE=60 keeps 40% of step 2's time for step 3.
# STEPS="3" runs only the teacher (steps 1 and 2 were measured already); TEACHER_SET="key=value ..." adds
# --set overrides to it. The teacher's last checkpoint comes back too (ckpt.tgz.part-*), so that it can
# be evaluated on the CPU machine beside the CPU run.
# Warp compiles MuJoCo Warp's kernels on a fresh machine (~4 minutes for FT and 1 more for VT on an
# H200, 2026-11-26); the steps after the first reuse them. The kernel cache travels in slices, a job
# or two each way (benchmarks/gpu_kernel_cache.py): carried into /tmp/gpu/kernels, it is restored first.
set -uo pipefail
budget=${1:?usage: gpu_session.sh SECONDS}
deadline=$((SECONDS + budget))
OUT=${OUT:?the device machine sets OUT}
res=/tmp/res && mkdir -p "$res"
log="$OUT/log.txt"
exec > >(tee -a "$log") 2>&1

left() { echo $((deadline - SECONDS)); }
# share PERCENT: seconds for the next step, PERCENT of what is left minus the packing at the end
# (at least 1: `timeout 0` would mean no limit at all)
share() { local s=$(((deadline - SECONDS - 25) * $1 / 100)); echo $((s > 0 ? s : 1)); }
stamp() { echo "== $(date -u +%H:%M:%S) [$(left) s left] $*"; }

stamp "install"
cp .gpu/p2/* /tmp/gpu/ && bash /tmp/gpu/install.sh || { echo "install failed"; exit 1; }
# MUJOCO_GL=disable: the image has no EGL, and `import mujoco` would load it for rendering
export PYTHONPATH=/tmp/site:$PWD UNIMAL_DATA=$PWD/.gpu/data PYTHONUNBUFFERED=1 MUJOCO_GL=disable
# Warp's kernels compiled on an earlier machine, carried in by the jobs before (results/gpu/LEDGER.md, "The
# kernel cache"): a hit loads a module instead of compiling it, the ~4-6 minutes a fresh machine spends
# A small cache (one group, ~1.4 MiB for FT/PointNav) can instead travel with this job: carry .gpu/kernels
if [ ! -d /tmp/gpu/kernels ] && compgen -G ".gpu/kernels/k*/kernels.*" > /dev/null; then
  mkdir -p /tmp/gpu/kernels && cp .gpu/kernels/k*/kernels.* /tmp/gpu/kernels/
fi
[ -d /tmp/gpu/kernels ] && python3 benchmarks/gpu_kernel_cache.py restore /tmp/gpu/kernels
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name(0))"

STEPS=${STEPS:-1 2 3}
want() { [[ " $STEPS " == *" $1 "* ]]; }

want 1 && {
stamp "1. env steps/s on CUDA (100 official robots; worlds per robot: ${WORLDS:=32 128 512})"
# shellcheck disable=SC2086  # WORLDS is a list
timeout -k 20 -s INT "$(share 55)" python3 benchmarks/batched_throughput.py --morphologies unimals100-train \
  --tasks FT VT --robots 100 --worlds $WORLDS --devices cuda --ppo-presets --count-robots 0 \
  --seconds 3 --out "$res/batched_throughput_gpu.md"
echo "step 1 exit $?"
}

want 2 && {
stamp "2. PPO end to end on CUDA (100 official robots)"
# the paper size first (issue 28's target is for it); no single-env CPU rows (CPU numbers live elsewhere)
timeout -k 20 -s INT "$(share ${PPO_SHARE:-100})" python3 benchmarks/batched_throughput.py --morphologies unimals100-train \
  --tasks --robots --devices cuda --ppo-robots 100 --ppo-worlds 128 --ppo-presets paper small --ppo-single-envs 0 \
  --count-robots 0 --out "$res/batched_ppo_gpu.md"
echo "step 2 exit $?"
}

# PPO_SHARE=60 leaves 40% of what is left after step 1 to the teacher (a first session measured it already)
# A run carried in by the job before this one (results/gpu/LEDGER.md: the chain of windows) resumes from its
# latest checkpoint; TEACHER_SET must repeat the settings it was begun with (run.json refuses others).
if [ -d /tmp/resume/teachers ]; then
  mkdir -p /tmp/gpu-run && cp -r /tmp/resume/. /tmp/gpu-run/
  echo "resuming: $(cat /tmp/gpu-run/teachers/FT/checkpoints/latest.json 2>/dev/null)"
fi
if want 3 && [ "$(share 100)" -gt 60 ]; then
  stamp "3. paper-size FT teacher (gpu profile, 100 official robots)"
  timeout -k 20 -s INT "$(share 100)" python3 -m divmorph teachers --profile gpu --out /tmp/gpu-run \
    --train-robots unimals100-train --task FT --no-progress --set teachers.checkpoint_every=1000000 $(for kv in ${TEACHER_SET:-}; do printf -- "--set %s " "$kv"; done)
  echo "step 3 exit $?"
fi

# 4. The transfer race of issue 42 on the device (results/gpu/LEDGER.md, lines R1-): the cpu100 teachers and
# students (tracked files) fine-tuned and scratch trained on MuJoCo Warp, every curve point evaluated on the
# device against many draws (transfer.eval_backend: batched, 15 episodes of 20 training + 20 held-out robots).
# RACE_TASKS, RACE_ARMS, RACE_SEEDS, RACE_STEPS pick the runs. A race folder is one budget (race-<RACE_STEPS>[-<RACE_TAG>]:
# its run.json records the settings, and a later window must repeat them); one carried in (.gpu/race copied
# to /tmp/resume/race by the job before) is restored over a fresh branch: its runs resume from their
# checkpoints, finished ones are skipped.
if want 4 && [ "$(share 100)" -gt 60 ]; then
  : "${RACE_TASKS:=PointNav}" "${RACE_ARMS:=scratch}" "${RACE_SEEDS:=0}" "${RACE_STEPS:=10000000}"
  race="race-$RACE_STEPS${RACE_TAG:+-$RACE_TAG}"  # RACE_TAG: a second race at the same budget with other settings (RACE_SET)
  stamp "4. the transfer race on the device: $RACE_TASKS x $RACE_ARMS x seeds $RACE_SEEDS, $RACE_STEPS steps ($race)"
  [ -d "/tmp/$race" ] || python3 -m divmorph branch --from results/cpu100 --out "/tmp/$race"
  carried=/tmp/resume/race  # a job before copied it there, or (small: ~1 MB a run) it travels with this job
  [ -d "$carried" ] || carried=.gpu/race
  if [ -f "$carried/$race/run.json" ]; then  # the race's own records (settings, robots) and runs
    cp -r "$carried/$race/." "/tmp/$race/" && echo "resuming $race: $(ls -d /tmp/$race/transfer/*/*/seed-* | wc -l) runs"
  fi
  # 90%: the rest of the window packs what the race wrote
  # shellcheck disable=SC2086  # the lists are word lists
  timeout -k 20 -s INT "$(share 90)" python3 -m divmorph transfer --profile cpu100 --out "/tmp/$race" --no-progress \
    $(for t in $RACE_TASKS; do printf -- "--task %s " "$t"; done) --arms "${RACE_ARMS// /,}" --seeds $RACE_SEEDS \
    --set device=cuda --set torch_threads=8 --set transfer.env_backend=batched --set transfer.worlds_per_robot=16 \
    --set transfer.terrain_variants=32 --set transfer.eval_backend=batched --set transfer.eval_episodes=15 \
    --set transfer.eval_every=1000000 --set transfer.checkpoint_every=1000000 --set transfer.n_timesteps="$RACE_STEPS" \
    --set transfer.task_gates=closest --set "transfer.overrides={n_steps: 32, batch_size: 6400, n_epochs: 4, learning_rate: lin_1e-3}" \
    $(for kv in ${RACE_SET:-}; do printf -- "--set %s " "$kv"; done)
  echo "step 4 exit $?"
  # the race's records (run.json, robot_sets.json) and every run's curves, logs and records; the latest
  # checkpoint only of the runs that did not finish (models of finished runs stay: made again by the commands)
  mkdir -p "$res/race/$race" && cp "/tmp/$race/run.json" "/tmp/$race/robot_sets.json" "$res/race/$race/"
  (cd "/tmp/$race" && find transfer -type f ! -path "*/checkpoints/*" ! -name "*.zip" ! -name "*.pkl" -print0 |
    tar --null -T - -cf - | tar -C "$res/race/$race" -xf -)
  for run in /tmp/"$race"/transfer/*/*/seed-*; do
    [ -f "$run/done.json" ] && continue
    [ -f "$run/checkpoints/latest.json" ] && (cd /tmp && tar -rf /tmp/race-ckpt.tar "${run#/tmp/}/checkpoints")
  done
  [ -f /tmp/race-ckpt.tar ] && gzip -c /tmp/race-ckpt.tar | split -b 15M - "$OUT/race-ckpt.tgz.part-"
fi

stamp "packing"
# the teacher's run without its checkpoints (40 MB each at the paper size: more than a job brings back)
[ -d /tmp/gpu-run ] && mkdir -p "$res/gpu-run" && tar -C /tmp/gpu-run --exclude=checkpoints -cf - . 2>/dev/null | tar -C "$res/gpu-run" -xf -
latest=$(ls -d /tmp/gpu-run/teachers/FT/checkpoints/step-* 2>/dev/null | sort | tail -1)
[ -n "$latest" ] && tar -C "$(dirname "$latest")" -czf /tmp/ckpt.tgz "$(basename "$latest")" && split -b 15M /tmp/ckpt.tgz "$OUT/ckpt.tgz.part-"
tar -C "$res" -czf /tmp/results.tgz . && split -b 15M /tmp/results.tgz "$OUT/results.tgz.part-"
ls -la "$OUT"
stamp "done"
