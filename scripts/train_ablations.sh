#!/usr/bin/env bash
# Thesis §7.8 (Table 7.2): train the baseline DefGraspNets and its four ablations V1-V4 on one split of one
# data set, then evaluate them together (scripts/evaluate.py ablations=true).
#
#   DATA=data/grasps OUT=logs/ablations bash scripts/train_ablations.sh [train.py overrides ...]
#   PARALLEL=2 DATA=... bash scripts/train_ablations.sh trainer=cpu model.latent=32 trainer.max_time=00:00:08:00
#
# Env: DATA (shard directory, required), OUT (runs and evaluation; default logs/ablations/<time>), PARALLEL
# (trainings at once; default 1), GPUS (with trainer=gpu: the k-th model trains on GPU k mod GPUS, through
# CUDA_VISIBLE_DEVICES; unset: every training sees all GPUs), STRIDE (V2's data.ramp_stride: ramp steps /
# model.num_steps; default 2, for 10-step ramps and the default 5 rollout steps), EVAL (extra
# scripts/evaluate.py overrides).
# The overrides go to every training (the same split, steps, size and budget for all five models). Once a model
# fails no further one starts (there will be no table); the ones already running finish.
set -euo pipefail
cd "$(dirname "$0")/.."
: "${DATA:?set DATA to the shard directory}"
OUT=${OUT:-logs/ablations/$(date +%Y-%m-%d_%H-%M-%S)}
PARALLEL=${PARALLEL:-1}
STRIDE=${STRIDE:-2}
mkdir -p "$OUT"
declare -A EXTRA=([baseline]="" [v1_separate]="" [v2_multi_step]="data.ramp_stride=$STRIDE" [v3_total_force]="" [v4_node_force]="")
train() {
  local name=$1 k=$2; shift 2
  local experiment=defgraspnets${name#baseline}; experiment=${experiment/defgraspnetsv/defgraspnets_v}
  if [ -n "${GPUS:-}" ]; then
    export CUDA_VISIBLE_DEVICES=$(( k % GPUS ))
    echo "$name on GPU $CUDA_VISIBLE_DEVICES"
  fi
  # shellcheck disable=SC2086
  python train.py experiment="$experiment" data.data_dir="$DATA" hydra.run.dir="$OUT/$name" logger=csv \
    ${EXTRA[$name]} "$@" > "$OUT/$name.log" 2>&1 && touch "$OUT/$name.trained" && echo "trained $name" \
    || { touch "$OUT/$name.failed"; echo "FAILED $name (see $OUT/$name.log)"; }
}
NAMES=(baseline v1_separate v2_multi_step v3_total_force v4_node_force)
rm -f "$OUT"/*.trained "$OUT"/*.failed
for k in "${!NAMES[@]}"; do
  name=${NAMES[$k]}
  # a failed model means no table: launch no further ones (those running finish)
  compgen -G "$OUT/*.failed" > /dev/null && { echo "not starting $name: a model failed"; continue; }
  train "$name" "$k" "$@" &
  while (( $(jobs -rp | wc -l) >= PARALLEL )); do wait -n || true; done
done
wait
for name in "${NAMES[@]}"; do
  [ -f "$OUT/$name.trained" ] || { echo "$name did not train (see $OUT/$name.log): no ablation table"; exit 1; }
done
ckpts=$(printf '%s,' "$OUT"/{baseline,v1_separate,v2_multi_step,v3_total_force,v4_node_force}/checkpoints/last.ckpt)
# shellcheck disable=SC2086
python scripts/evaluate.py "ckpt_paths=[${ckpts%,}]" ablations=true hydra.run.dir="$OUT/evaluation" ${EVAL:-}
echo "ablation table: $OUT/evaluation/results.md"
