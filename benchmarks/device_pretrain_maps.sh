#!/usr/bin/env bash
# Second-stage GSFixer pretraining on a lent GPU, in one call: the packaged base trained on the
# triplets of our own maps (pretrain.maps: each scene's TSDF mesh and Gaussian map rendered at its
# novel views), two learning rates side by side, each for STAGE2_S seconds.
#
# The map triplets are built on the CPU beforehand (the GPU image has no Open3D):
#   gsfix-online fixer pretrain --out DIR pretrain.maps.views=8 ... writes DIR/maps, or
#   load_or_build_map_triplets for the seeds below; then
#   tar -cJf .gpu/maps.tar.xz -C DIR maps        (seeds FIRST..99; FIRST=34 fits the 64 MiB carry)
# and the call carries .gpu/maps.tar.xz and .gpu/whl (diffusers, kornia, kornia_rs, plyfile).
# Everything lands in $OUT: device.log, stage2_<lr>.tar.part-* (base/, pretrain.json, config.yaml;
# `cat stage2_<lr>.tar.part-* | tar -x`).
set -u
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/device_stage2}
FIRST=${FIRST:-34}
STAGE2_S=${STAGE2_S:-240}
LRS=${LRS:-1e-4 3e-4}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/device.log") 2>&1
t0=$(date +%s)
stamp() { echo "[$(($(date +%s) - t0)) s] $*"; }

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .gpu/whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
mkdir -p .gpu/stage2 && tar -xJf .gpu/maps.tar.xz -C .gpu/stage2 || exit 1
stamp "$(find .gpu/stage2/maps -name '*.npz' | wc -l) map-triplet scenes unpacked"

pids=()
for lr in $LRS; do
  run=.gpu/stage2/run_$lr
  mkdir -p "$run" && ln -sfn ../maps "$run/maps"
  stamp "stage 2 at lr $lr for $STAGE2_S s"
  OMP_NUM_THREADS=6 python3 -m gsfix_online.cli fixer pretrain --out "$run" --no-progress \
    pretrain.seed="$FIRST" pretrain.scenes=$((100 - FIRST)) pretrain.val_scenes=6 \
    pretrain.variants=0 pretrain.maps.views=8 pretrain.init=gsfix_online/fixer/weights/base \
    pretrain.steps=1000000 pretrain.time_limit_s="$STAGE2_S" pretrain.eval_every=500 \
    pretrain.save_every=1000000 pretrain.train.lr="$lr" pretrain.train.batch_size=32 \
    pretrain.train.grad_accum=1 pretrain.train.crop=32 pretrain.train.ema_decay=0.999 \
    pretrain.train.seed=0 fixer.masks.p_shared=0.5 fixer.masks.p_gs_only=0.5 \
    >"$OUT/stage2_$lr.log" 2>&1 &
  pids+=($!)
done
wait "${pids[@]}"  # not a bare wait: it would wait for the tee of this script's output too
for lr in $LRS; do
  run=.gpu/stage2/run_$lr
  tail -3 "$OUT/stage2_$lr.log"
  tar -cf - -C "$run" base pretrain.json config.yaml | split -b 15000000 - "$OUT/stage2_$lr.tar.part-"
done
stamp "done"
