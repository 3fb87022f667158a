#!/usr/bin/env bash
# Spread `datagen/grasps.py` over the GPUs of one machine: WORKERS_PER_GPU worker processes per GPU (default
# 1; worker k on device cuda:(k mod NGPU)) each walk the whole object set as one Hydra multirun and simulate
# the objects they claim first (`claim_dir`, an atomic mkdir per object): a worker that finished an object
# takes the next unclaimed one, so a slow object holds up no other GPU. Every shard is resumable, so a second
# call carries on where a stopped one left off.
#   bash scripts/grasp_datagen_gpus.sh NGPU OBJECT_SET [DATAGEN_OVERRIDES...]
#   e.g. the thesis-scale set (§7.4; configs/datagen/grasps.yaml) on a 4-GPU machine, 10 moduli per object:
#   bash scripts/grasp_datagen_gpus.sh 4 all num_grasps=100 steps=50 target_nodes=1000 stream_slots=128 \
#       'youngs_modulus=[1e4,2.154e4,4.642e4,1e5,2.154e5,4.642e5,1e6,2.154e6,4.642e6,1e7]'
#   and at the thesis's count (one modulus per object, all ten on the level-2 object), 2 workers per GPU:
#   WORKERS_PER_GPU=2 bash scripts/grasp_datagen_gpus.sh 4 all num_grasps=100 steps=50 target_nodes=1000 \
#       stream_slots=128 moduli_per_object=1 'all_moduli_objects=[cuboid_30x30x30]' \
#       'youngs_modulus=[1e4,2.154e4,4.642e4,1e5,2.154e5,4.642e5,1e6,2.154e6,4.642e6,1e7]'
# OBJECT_SET: a file stem of configs/objects/ (all, primitives, real, ci_small). NGPU=0 runs 2 CPU workers
# (device=cpu) instead, for a try on a machine without a GPU. Env OUT (default logs/grasp_datagen_gpus) holds
# each worker's log, the claims, and summary.txt: per worker its objects, seconds and the shards' own
# summary lines.
set -uo pipefail
cd "$(dirname "$0")/.."
ngpu=${1:?number of GPUs (0: two CPU workers)}
set_name=${2:?object set: a file stem of configs/objects/}
shift 2
per_gpu=${WORKERS_PER_GPU:-1}
[[ $per_gpu =~ ^[1-9][0-9]*$ ]] || { echo "WORKERS_PER_GPU must be a positive integer, got '$per_gpu'" >&2; exit 2; }
list=configs/objects/$set_name.yaml
[[ -f $list ]] || { echo "no object set $list" >&2; exit 2; }
mapfile -t objects < <(sed -n 's/^  - \([A-Za-z0-9_.-]*\).*/\1/p' "$list")
((${#objects[@]})) || { echo "object set $list lists no names" >&2; exit 2; }
workers=$((ngpu * per_gpu))
((ngpu > 0)) || workers=2
out=${OUT:-logs/grasp_datagen_gpus}
mkdir -p "$out"
claims=$(cd "$out" && pwd)/claims
rm -rf "$claims"  # claims are per run; the shards themselves say what is finished
start=$(date +%s)
: > "$out/summary.txt"
all=$(IFS=,; echo "${objects[*]}")
for ((k = 0; k < workers; k++)); do
    device=cpu
    ((ngpu > 0)) && device=cuda:$((k % ngpu))
    (
        t0=$(date +%s)
        python datagen/grasps.py -m "object=$all" device="$device" progress=false claim_dir="$claims" "$@" \
            hydra.sweep.dir="$out/worker_$k" > "$out/worker_$k.log" 2>&1
        rc=$?
        mine=$(sed -n 's/.*claimed object \([A-Za-z0-9_.-]*\) for this worker.*/\1/p' "$out/worker_$k.log")
        n=$(printf '%s' "$mine" | grep -c .)
        echo "worker $k ($device, rc $rc): $n objects in $(($(date +%s) - t0)) s: $(echo $mine)" >> "$out/summary.txt"
    ) &
done
wait
echo "all workers: ${#objects[@]} objects in $(($(date +%s) - start)) s" >> "$out/summary.txt"
cat "$out/summary.txt"
grep -h "h5: .*\(squeeze ramps solved\|already finished\)" "$out"/worker_*.log 2>/dev/null | sed "s/.*INFO\] - //"
