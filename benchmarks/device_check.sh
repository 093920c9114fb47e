#!/usr/bin/env bash
# The CUDA checks on a lent GPU machine, in one call (its image has torch, no registry access):
#   1. gsplat's CUDA extension builds (in the background, while 2 runs);
#   2. GSFixer pretraining on the GPU for PRETRAIN_S seconds (0: none; the packaged base is timed),
#      on the scene cache in .gpu/pre/scenes
#      (rendered here: `gsfix-online fixer pretrain` writes it; Open3D is not on that machine);
#      PRETRAIN_MODEL adds overrides of the model (e.g. a bigger U-Net than the packaged base);
#   3. GSFixer repair / fine-tuning speed of what was pretrained (benchmarks/bench_cuda.py);
#      SD2=1 adds the Stable Diffusion 2-size model;
#   4. the GPU tests (gsplat against the CPU rasterizer, the mapper on CUDA) and render speed.
# Wheels the image lacks travel in .whl (diffusers, kornia, kornia_rs, gsplat, plyfile).
# Everything lands in $OUT: device.log, gsplat_build.log, pretrain_base.tar.part-*, cuda_*.json
# (files come back in parts of at most 15 MB: `cat pretrain_base.tar.part-* | tar -x`).
set -u
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/device_check}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/device.log") 2>&1
t0=$(date +%s)
stamp() { echo "[$(($(date +%s) - t0)) s] $*"; }

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD

stamp "building gsplat's CUDA extension in the background (sm_90)"
(
  MAX_JOBS=12 TORCH_CUDA_ARCH_LIST=9.0 python3 -c "from gsplat.cuda._backend import _C; print('gsplat extension loaded:', _C is not None)"
  echo "build exit $?"
) >"$OUT/gsplat_build.log" 2>&1 &
build=$!

BASE=gsfix_online/fixer/weights/base
if [ "${PRETRAIN_S:-200}" -gt 0 ]; then
  stamp "pretraining GSFixer on the GPU for ${PRETRAIN_S:-200} s (model overrides: ${PRETRAIN_MODEL:-none})"
  # shellcheck disable=SC2086  # PRETRAIN_MODEL is a list of overrides
  python3 -m gsfix_online.apps.cli fixer pretrain --out .gpu/pre --no-progress \
    pretrain.scenes=96 pretrain.val_scenes=2 pretrain.variants=4 pretrain.steps=1000000 \
    pretrain.time_limit_s="${PRETRAIN_S:-200}" pretrain.eval_every=1000 pretrain.save_every=2000 \
    pretrain.train.lr=3e-4 pretrain.train.batch_size=32 pretrain.train.grad_accum=1 \
    pretrain.train.crop=32 pretrain.train.ema_decay=0.999 pretrain.train.seed=0 \
    fixer.masks.p_shared=0.5 fixer.masks.p_gs_only=0.5 ${PRETRAIN_MODEL:-}
  cp .gpu/pre/pretrain.json "$OUT/pretrain.json"
  tar -cf - -C .gpu/pre base pretrain.json config.yaml | split -b 15000000 - "$OUT/pretrain_base.tar.part-"
  BASE=.gpu/pre/base
fi

stamp "GSFixer speed: $BASE${SD2:+, and SD2 size}"
python3 benchmarks/bench_cuda.py --sections fixer ${SD2:+sd2} --repeats 3 --cpu-threads 0 \
  --base "$BASE" --out "$OUT/cuda_fixer.json"

stamp "waiting for the gsplat build"
wait $build
tail -5 "$OUT/gsplat_build.log"
stamp "GPU tests"
python3 -m pytest -q -p no:cacheprovider -m gpu tests/mapping/splat/test_render_cpu.py tests/mapping/splat/test_mapper.py
stamp "render speed: gsplat against the CPU rasterizer"
python3 benchmarks/bench_cuda.py --sections render --repeats 5 --out "$OUT/cuda_render.json"
stamp "done"
