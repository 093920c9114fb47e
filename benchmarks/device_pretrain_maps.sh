#!/usr/bin/env bash
# Second-stage GSFixer pretraining on a lent GPU: the packaged base trained on the triplets of our
# own maps (pretrain.maps: each scene's TSDF mesh and Gaussian map rendered at its novel views),
# with VARIANTS > 0 mixed with the synthetic degradations of the same scenes, at each learning
# rate in LRS side by side for STAGE2_S seconds.
#
# The GPU image has no Open3D, so the scenes and their maps are rendered on the CPU beforehand
# (`make pretrain-stage2`, or `gsfix-online fixer pretrain --out DIR pretrain.maps.views=8 ...`,
# writes DIR/scenes and DIR/maps), re-saved as uncompressed npz (xz packs raw images a fifth
# smaller than zlib npz does) and packed:
#   tar -cf - -C DIR maps | xz -9 > .gpu/maps.tar.xz       (and scenes -> .gpu/scenes.tar.xz)
# A call carries at most 64 MiB with the tracked tree, so a mixed corpus takes two calls on the
# same warm machine: PHASE=stage carries .gpu/whl and .gpu/scenes.tar.xz, installs the wheels
# (diffusers, kornia, kornia_rs, plyfile) into outputs/gpu_site and unpacks into outputs/gpu_stage2; the next
# call (PHASE=train, the default) carries .gpu/maps.tar.xz and trains. outputs/ is in .gitignore,
# so the warm machine keeps them between the calls; a fresh machine lacks them and the train
# phase says so at once. Maps alone (VARIANTS=0, FIRST=34) fit one call with .gpu/whl.
# Every .gpu/*.tar.xz a call carries is unpacked: a corpus too big for one call (the map triplets
# with held-out frames, MAP_HOLDOUT=5) is split into tarballs, each staged by a PHASE=stage call.
# Everything lands in $OUT: device.log, stage2_<lr>.tar.part-* (base/, pretrain.json,
# config.yaml; `cat stage2_<lr>.tar.part-* | tar -x`).
set -u
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/device_stage2}
PHASE=${PHASE:-train}
FIRST=${FIRST:-34}
VARIANTS=${VARIANTS:-0}
STAGE2_S=${STAGE2_S:-240}
LRS=${LRS:-1e-4 3e-4}
MAP_HOLDOUT=${MAP_HOLDOUT:-0}  # pretrain.maps.holdout the map triplets were built with
STAGE=outputs/gpu_stage2  # outputs/ is in .gitignore: a warm machine keeps it between calls
SITE=outputs/gpu_site
mkdir -p "$OUT" "$STAGE"
exec > >(tee -a "$OUT/device.log") 2>&1
t0=$(date +%s)
stamp() { echo "[$(($(date +%s) - t0)) s] $*"; }

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
if [ ! -d "$SITE" ]; then
  [ -d .gpu/whl ] || { echo "no $SITE and no .gpu/whl carried: run PHASE=stage first"; exit 2; }
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$SITE" \
    .gpu/whl/*.whl || exit 1
fi
export PYTHONPATH=$PWD/$SITE:$PWD
for tarball in .gpu/*.tar.xz; do  # maps.tar.xz, scenes.tar.xz, or a corpus split over calls
  [ -f "$tarball" ] || continue
  tar -xJf "$tarball" -C "$STAGE" && rm -f "$tarball" || exit 1  # unpacked once per machine
  stamp "$tarball unpacked"
done
n_maps=$(find "$STAGE/maps" -name '*.npz' 2>/dev/null | wc -l)
n_scenes=$(find "$STAGE/scenes" -name '*.npz' 2>/dev/null | wc -l)
stamp "$n_maps map-triplet scenes, $n_scenes synthetic scenes in $STAGE"
[ "$PHASE" = stage ] && { stamp "staged"; exit 0; }
[ "$n_maps" -gt 0 ] || { echo "no map triplets in $STAGE/maps"; exit 2; }
if [ "$VARIANTS" -gt 0 ]; then
  [ "$n_scenes" -gt 0 ] || { echo "VARIANTS=$VARIANTS but no scenes in $STAGE: PHASE=stage first"; exit 2; }
  FIRST=0
fi

pids=()
for lr in $LRS; do
  run=$STAGE/run_$lr
  mkdir -p "$run" && ln -sfn ../maps "$run/maps" && ln -sfn ../scenes "$run/scenes"
  stamp "stage 2 at lr $lr for $STAGE2_S s (variants $VARIANTS, scenes $FIRST..99)"
  OMP_NUM_THREADS=6 python3 -m gsfix_online.apps.cli fixer pretrain --out "$run" --no-progress \
    pretrain.seed="$FIRST" pretrain.scenes=$((100 - FIRST)) pretrain.val_scenes=6 \
    pretrain.variants="$VARIANTS" pretrain.maps.views=8 pretrain.maps.holdout="$MAP_HOLDOUT" \
    pretrain.init=gsfix_online/fixer/weights/base \
    pretrain.steps=1000000 pretrain.time_limit_s="$STAGE2_S" pretrain.eval_every=500 \
    pretrain.save_every=1000000 pretrain.train.lr="$lr" pretrain.train.batch_size=32 \
    pretrain.train.grad_accum=1 pretrain.train.crop=32 pretrain.train.ema_decay=0.999 \
    pretrain.train.seed=0 fixer.masks.p_shared=0.5 fixer.masks.p_gs_only=0.5 \
    >"$OUT/stage2_$lr.log" 2>&1 &
  pids+=($!)
done
wait "${pids[@]}"  # not a bare wait: it would wait for the tee of this script's output too
for lr in $LRS; do
  run=$STAGE/run_$lr
  tail -3 "$OUT/stage2_$lr.log"
  tar -cf - -C "$run" base pretrain.json config.yaml | split -b 15000000 - "$OUT/stage2_$lr.tar.part-"
done
stamp "done"
