#!/usr/bin/env bash
# Spread `datagen/grasps.py` over the GPUs of one machine: the objects of an object set are dealt round-robin
# to NGPU worker processes, worker k on device cuda:k, each running its objects one after another as one Hydra
# multirun (one process per GPU: processes sharing a GPU are slower than one, see README). Every shard is
# resumable, so a second call carries on where a stopped one left off.
#   bash scripts/grasp_datagen_gpus.sh NGPU OBJECT_SET [DATAGEN_OVERRIDES...]
#   e.g. the thesis-scale set (§7.4; configs/datagen/grasps.yaml) on a 4-GPU machine:
#   bash scripts/grasp_datagen_gpus.sh 4 all num_grasps=100 steps=50 target_nodes=1000 stream_slots=128 \
#       'youngs_modulus=[1e4,2.154e4,4.642e4,1e5,2.154e5,4.642e5,1e6,2.154e6,4.642e6,1e7]'
# OBJECT_SET: a file stem of configs/objects/ (all, primitives, real, ci_small). NGPU=0 runs 2 CPU workers
# (device=cpu) instead, for a try on a machine without a GPU. Env OUT (default logs/grasp_datagen_gpus) holds
# each worker's log, and summary.txt: per worker its objects, seconds and the shards' own summary lines.
set -uo pipefail
cd "$(dirname "$0")/.."
ngpu=${1:?number of GPUs (0: two CPU workers)}
set_name=${2:?object set: a file stem of configs/objects/}
shift 2
list=configs/objects/$set_name.yaml
[[ -f $list ]] || { echo "no object set $list" >&2; exit 2; }
mapfile -t objects < <(sed -n 's/^  - \([A-Za-z0-9_.-]*\).*/\1/p' "$list")
((${#objects[@]})) || { echo "object set $list lists no names" >&2; exit 2; }
workers=$ngpu
((ngpu > 0)) || workers=2
out=${OUT:-logs/grasp_datagen_gpus}
mkdir -p "$out"
start=$(date +%s)
: > "$out/summary.txt"
for ((k = 0; k < workers; k++)); do
    mine=()
    for ((i = k; i < ${#objects[@]}; i += workers)); do mine+=("${objects[i]}"); done
    ((${#mine[@]})) || continue
    device=cpu
    ((ngpu > 0)) && device=cuda:$k
    (
        t0=$(date +%s)
        python datagen/grasps.py -m "object=$(IFS=,; echo "${mine[*]}")" device="$device" progress=false "$@" \
            hydra.sweep.dir="$out/worker_$k" > "$out/worker_$k.log" 2>&1
        rc=$?
        echo "worker $k ($device, rc $rc): ${#mine[@]} objects in $(($(date +%s) - t0)) s: ${mine[*]}" >> "$out/summary.txt"
    ) &
done
wait
echo "all workers: ${#objects[@]} objects in $(($(date +%s) - start)) s" >> "$out/summary.txt"
cat "$out/summary.txt"
grep -h "h5: .*\(squeeze ramps solved\|already finished\)" "$out"/worker_*.log 2>/dev/null | sed "s/.*INFO\] - //"
