#!/usr/bin/env bash
# How the shipped wrench-CNN checkpoints were made (thesis §3.3-3.4), on one many-core GPU machine:
#   bash scripts/wrench_pipeline.sh generate SECONDS [POKE_WORKERS] [FOREARM_WORKERS]
#   bash scripts/wrench_pipeline.sh train SECONDS_PER_MODEL OUT_DIR [TRAIN_OVERRIDES...]
# generate: independent `datagen/tactile.py` processes, each working through its own interleaved shards
#   of the full poking (200 shards) and forearm (40 shards) grids until the time budget is spent; every
#   shard is resumable and spread over the whole grid, so the finished ones are a fair subset and a
#   second call carries on where this one stopped. (Any job runner does the same: each shard is one
#   independent Hydra run, e.g. `python datagen/tactile.py -m shard_index='range(0,200)' shard_count=200`.)
#   Env REPEATS (default 1): passes over the forearm grid, given to its shards as repeats=$REPEATS
#   (thesis: 5, the grid and 4 perturbed repeats; configs/datagen/tactile.yaml). Keep it fixed for a
#   data directory: the shards interleave the repeated grid, so shards made with another value do not
#   fit together. Poking never repeats. Training splits the forearm set by grid state (all repeats of a
#   state on one side, defgraspnets.data.tactile_datamodule).
# generate-gpu: one process on one GPU (device=cuda) working through shards 0.. of every STRIDE-th path
#   of the DATASET grid split into SHARD_COUNT interleaved shards, each shard's paths streamed through
#   env BATCH (default 64) problems (datagen's stream=true: a problem takes the next path as soon as it
#   finished one; finished paths are written BATCH at a time) until SECONDS are spent (a shard cut short
#   resumes on the next call):
#   bash scripts/wrench_pipeline.sh generate-gpu DATASET STRIDE SHARD_COUNT [SECONDS]
#   e.g. BATCH=128 generate-gpu poke 1 1 (the whole 10,000-state grid as one stream: 8.1 min on an
#   H100 without shard writing, session 35; as 2 shards, `poke 1 2`, 306.8 + 290.0 s and 608 s end to
#   end with 1.2 GB of HDF5, session 36), generate-gpu forearm 1 1 (one forearm pass, 1962 states:
#   185.6 s) and REPEATS=5 BATCH=128 generate-gpu forearm 1 1 (the five-pass forearm set, 9810 states:
#   659.5 s on an H200, session 37). Each shard drains its stream once (a tail of a few slow
#   paths), so fewer, larger shards are faster. Many processes on one GPU are slower than one.
# train: the three models of §3.4 on the finished shards (trainer.max_time bounds each), then
#   scripts/evaluate_wrench.py and scripts/benchmark_wrench_cnn.py; results into OUT_DIR.
set -uo pipefail
cd "$(dirname "$0")/.."
phase=${1:?generate, generate-gpu or train}
REPEATS=${REPEATS:-1}

run_shards() {  # dataset shard_count worker workers deadline stride [datagen overrides...]
    local dataset=$1 count=$2 worker=$3 workers=$4 deadline=$5 stride=$6 i left extra=("${@:7}")
    [[ $dataset == forearm ]] && extra+=(repeats="$REPEATS")
    for ((i = worker; i < count; i += workers)); do
        left=$((deadline - $(date +%s)))
        ((left > 10)) || break
        timeout "$left" python datagen/tactile.py dataset="$dataset" stride="$stride" limit=null \
            shard_count="$count" shard_index="$i" shard_name="$(printf 'shard_%03d' "$i")" ${extra[@]+"${extra[@]}"} \
            progress=false hydra.run.dir="logs/datagen_tactile/$dataset/$(printf '%03d' "$i")" || break
    done
}

if [[ $phase == generate ]]; then
    budget=${2:?seconds}
    poke_workers=${3:-12}
    forearm_workers=${4:-4}
    deadline=$(($(date +%s) + budget))
    for ((w = 0; w < poke_workers; w++)); do run_shards poke 200 "$w" "$poke_workers" "$deadline" 1 & done
    for ((w = 0; w < forearm_workers; w++)); do run_shards forearm 40 "$w" "$forearm_workers" "$deadline" 1 & done
    wait
    for d in poke forearm; do
        echo "$d: $(ls data/tactile/$d/*.h5 2>/dev/null | wc -l) finished shards"
        grep -h "samples," logs/datagen_tactile/$d/*/*.log 2>/dev/null | sed 's/.*INFO\] - //'
    done
elif [[ $phase == generate-gpu ]]; then
    dataset=$2
    stride=${3:?stride}
    count=${4:?shard count}
    deadline=$(($(date +%s) + ${5:-86400}))
    run_shards "$dataset" "$count" 0 1 "$deadline" "$stride" device=cuda batch_size="${BATCH:-64}"
    grep -h "samples," logs/datagen_tactile/"$dataset"/*/*.log 2>/dev/null | sed 's/.*INFO\] - //'
elif [[ $phase == train ]]; then
    budget=${2:?seconds}
    out=${3:?output directory}
    shift 3  # the rest: overrides for train.py, e.g. data.batch_size=16
    mkdir -p "$out"
    for m in poke forearm combined; do
        python train.py experiment=wrench_$m trainer=gpu trainer.max_epochs=100000 \
            trainer.max_time="$(printf '00:00:%02d:%02d' $((budget / 60)) $((budget % 60)))" \
            logger=csv hydra.run.dir="$out/run_$m" "$@" > "$out/train_$m.log" 2>&1
        grep -E "test/|Error" "$out/train_$m.log"
        best=$(ls "$out/run_$m/checkpoints"/epoch_*.ckpt | head -1)
        cp "$best" "$out/wrench_$m.ckpt"
    done
    python scripts/evaluate_wrench.py ckpts.poke="$out/wrench_poke.ckpt" ckpts.forearm="$out/wrench_forearm.ckpt" \
        ckpts.combined="$out/wrench_combined.ckpt" device=cuda hydra.run.dir="$out/eval" 2>&1 | grep -v Warn
    python scripts/benchmark_wrench_cnn.py device=cuda ckpt_path="$out/wrench_poke.ckpt" out="$out/wrench_cnn_cuda.json"
    python scripts/benchmark_wrench_cnn.py device=cpu ckpt_path="$out/wrench_poke.ckpt" out="$out/wrench_cnn_cpu_device_host.json"
else
    echo "unknown phase $phase (generate | generate-gpu | train)" >&2
    exit 2
fi
