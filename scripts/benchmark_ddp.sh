#!/usr/bin/env bash
# DDP scaling of DefGraspNets training: the same run on 1 and on N devices of one machine, same per-device
# batch size, training graphs/s summed over the ranks (callbacks/throughput: train/graphs_per_sec of the last
# epoch, warm-up batches and validation excluded) -> $OUT/benchmark_ddp.json.
#
#   bash scripts/benchmark_ddp.sh                                  # 1 vs 2 GPUs, thesis-size model
#   bash scripts/benchmark_ddp.sh trainer.precision=bf16-mixed     # extra Hydra overrides go to every run
#   ACCELERATOR=cpu DEVICES="1 2" LATENT=8 BLOCKS=1 OBJECTS=2 GRASPS=4 STEPS=2 DIVISIONS=4,3,3 PAD_N=3 \
#       BATCH=4 WORKERS=0 EPOCHS=1 WARMUP=1 bash scripts/benchmark_ddp.sh           # CPU smoke test (gloo)
#
# Data: synthetic grasp shards (the generator of tests/test_data_synthetic.py: structured tet boxes, square
# finger pads, smooth analytic fields; no FEM), written once to $DATA/grasps (the defaults: ~10 s,
# 72 MB). Defaults: 6 boxes of 50 mm with 11 x 11 x 13 = 1573 vertices (DIVISIONS=10,10,12) and two
# 25 x 25 = 625-vertex pads, i.e. graphs of thesis size (cf. scripts/benchmark_model.py), 40 grasps x 3 moduli
# x 10 force steps per box: ~5k training graphs per epoch. The graph construction (contact edges) runs in
# the DataLoader workers (WORKERS per rank), as in real training.
# Model: experiment=defgraspnets (latent 128, 15 blocks) at BATCH graphs per device (default 8).
# Env: ACCELERATOR (gpu), DEVICES ("1 2": one run per entry; 1 = trainer=default, >1 = trainer=ddp; empty:
#   only write the data),
#   BATCH, LATENT, BLOCKS, EPOCHS (2), WARMUP (warm-up batches per epoch, 20), WORKERS (4), OBJECTS, GRASPS,
#   STEPS, DIVISIONS, PAD_N, DATA (data/benchmark_ddp), OUT (logs/benchmark_ddp/<time>), PYTHON (python).
set -euo pipefail
cd "$(dirname "$0")/.."

ACCELERATOR=${ACCELERATOR:-gpu}
DEVICES=${DEVICES-"1 2"}
BATCH=${BATCH:-8}
LATENT=${LATENT:-128}
BLOCKS=${BLOCKS:-15}
EPOCHS=${EPOCHS:-2}
WARMUP=${WARMUP:-20}
WORKERS=${WORKERS:-4}
OBJECTS=${OBJECTS:-6}
GRASPS=${GRASPS:-40}
STEPS=${STEPS:-10}
DIVISIONS=${DIVISIONS:-10,10,12}
PAD_N=${PAD_N:-25}
DATA=${DATA:-data/benchmark_ddp}
OUT=${OUT:-logs/benchmark_ddp/$(date +%Y-%m-%d_%H-%M-%S)}
PYTHON=${PYTHON:-python}
case $DATA in /*) ;; *) DATA=$PWD/$DATA ;; esac
case $OUT in /*) ;; *) OUT=$PWD/$OUT ;; esac
mkdir -p "$OUT"

# ---------------------------------------------------------------------------------------------- data
if ! compgen -G "$DATA/grasps/*.h5" >/dev/null; then
    echo "writing synthetic shards to $DATA/grasps"
    "$PYTHON" - "$DATA/grasps" "$OBJECTS" "$GRASPS" "$STEPS" "$DIVISIONS" "$PAD_N" <<'EOF'
import sys
from pathlib import Path

sys.path.insert(0, "tests")
import test_data_synthetic as syn  # noqa: E402

from defgraspnets.data.grasp_schema import GraspShardWriter, shard_file_name  # noqa: E402

out, objects, grasps, steps = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
divisions, pad_n = tuple(int(v) for v in sys.argv[5].split(",")), int(sys.argv[6])
out.mkdir(parents=True, exist_ok=True)
fingers = syn.pad_fingers(pad_n)
for i in range(objects):
    size = (0.05, 0.05 - 0.002 * i, 0.05 + 0.002 * i)
    obj = syn.box_object(f"box{i}", size=size, divisions=divisions)
    pose, fpose, cdir = syn.grasp_poses(obj, grasps, seed=i)
    w = GraspShardWriter.create(
        out / shard_file_name(obj.name, 0, 1), obj, fingers, pose, fpose, cdir, steps,
        generator_version="benchmark_ddp", config="synthetic: true",
    )
    for k, g in w.pending():
        w.write(k, g, *syn.ramp_fields(obj, fpose[g], cdir[g], obj.youngs_modulus[k], steps))
    w.finalize()
    print(f"{obj.name}: {len(obj.points)} vertices + 2 x {len(fingers.vertices)} pad vertices, "
          f"{grasps} grasps x {len(obj.youngs_modulus)} moduli x {steps} steps", flush=True)
EOF
fi

[[ -n ${DEVICES// /} ]] || exit 0

# ---------------------------------------------------------------------------------------------- runs
for n in $DEVICES; do
    if [[ $n == 1 ]]; then trainer=default; else trainer=ddp; fi
    echo "training on $n $ACCELERATOR device(s) -> $OUT/devices_$n"
    "$PYTHON" train.py experiment=defgraspnets trainer=$trainer trainer.accelerator="$ACCELERATOR" \
        trainer.devices="$n" trainer.max_epochs="$EPOCHS" "callbacks=[default,throughput]" \
        callbacks.throughput.warmup_steps="$WARMUP" logger=csv test=false \
        model.latent="$LATENT" model.num_blocks="$BLOCKS" data.batch_size="$BATCH" \
        data.num_workers="$WORKERS" data.persistent_workers=true "data.eval_steps=[-1]" \
        paths.data_dir="$DATA" hydra.run.dir="$OUT/devices_$n" extras.print_config=false "$@" \
        >"$OUT/devices_$n.log" 2>&1 || { tail -30 "$OUT/devices_$n.log"; exit 1; }
done

# ---------------------------------------------------------------------------------------------- summary
"$PYTHON" - "$OUT" "$ACCELERATOR" "$*" $DEVICES <<'EOF'
import csv, json, platform, sys
from pathlib import Path

import torch

out, accelerator, overrides, devices = Path(sys.argv[1]), sys.argv[2], sys.argv[3], [int(d) for d in sys.argv[4:]]
runs = []
for n in devices:
    (metrics,) = (out / f"devices_{n}").glob("csv/version_*/metrics.csv")
    rows = [r for r in csv.DictReader(open(metrics)) if r.get("train/graphs_per_sec")]
    if not rows:
        sys.exit(f"{metrics}: no train/graphs_per_sec (epochs shorter than the warm-up?)")
    last = rows[-1]
    runs.append({
        "devices": n,
        "graphs_per_sec": float(last["train/graphs_per_sec"]),
        "graphs_per_sec_per_device": float(last["train/graphs_per_sec_per_device"]),
        "graphs_measured_last_epoch": int(float(last["train/throughput_graphs"])),
        "graphs_per_sec_per_epoch": [float(r["train/graphs_per_sec"]) for r in rows],
        "run_dir": str(out / f"devices_{n}"),
    })
base = next((r for r in runs if r["devices"] == 1), None)
for r in runs:
    if base:
        r["speedup"] = r["graphs_per_sec"] / base["graphs_per_sec"]
        r["efficiency"] = r["speedup"] / r["devices"]
device = torch.cuda.get_device_name(0) if accelerator == "gpu" and torch.cuda.is_available() else platform.processor() or "cpu"
result = {
    "what": "DefGraspNets training graphs/s summed over ranks, last epoch (callbacks/throughput)",
    "accelerator": accelerator,
    "device": device,
    "torch": torch.__version__,
    "overrides": overrides,
    "runs": runs,
}
(out / "benchmark_ddp.json").write_text(json.dumps(result, indent=2))
print(json.dumps(result, indent=2))
EOF
echo "wrote $OUT/benchmark_ddp.json"
