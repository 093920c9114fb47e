#!/usr/bin/env bash
# `make demo` end to end on a lent GPU machine, then the CUDA checks, in two calls on one warm
# machine. Its image has torch, CUDA and no registry access; Open3D alone is larger than what one
# call carries beside the tree, so the packages travel prepared and split:
#   .gpu/p1: gsplat's wheel, syslib.tar.xz (the shared libraries Open3D links and the image may
#            lack: X11, GL, udev), site.tar.xz.part-aa
#   .gpu/p2: site.tar.xz.part-ab, and any wheels the site lacks (pyinstrument for PROFILE=1)
# site.tar.xz is a site-packages tree made here: this project's wheel, Open3D's CPU wheel (its
# example and lighting assets left out) and the Python packages the image lacks, unpacked with
# `unzip` and packed with `tar -c | xz`.
#   PHASE=stage: keeps part aa and the libraries in /tmp, installs gsplat and starts building its
#                CUDA extension in a session of its own (it runs on while the machine is warm);
#   PHASE=run:   unpacks the site (the checkout's code over the wheel's), waits for the build,
#                runs the demo (in /tmp, so the installed package, with its nodes, is the one
#                imported; PROFILE=1 profiles its nodes), the GPU tests and, unless SKIP_BENCH=1,
#                the CUDA benches.
# The packages (.gpu/p1, .gpu/p2) are made as benchmarks/results/demo_h200.md says.
# Everything lands in $OUT: device.log, demo.tar.gz (summary, configuration, figure, metrics,
# report, graph log), views.tar, cuda_render.json, cuda_fixer.json.
set -u
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/device_demo}
PHASE=${PHASE:-run}
REPO=$PWD
mkdir -p "$OUT"
exec > >(tee -a "$OUT/device.log") 2>&1
t0=$(date +%s)
stamp() { echo "[$(($(date +%s) - t0)) s] $*"; }
untar_xz() {  # stdin: an xz-packed tar; $1: where to unpack (Python's lzma: the image may lack xz)
  python3 -c "import lzma, sys, tarfile
tarfile.open(fileobj=lzma.open(sys.stdin.buffer), mode='r|').extractall(sys.argv[1])" "$1"
}

if [ "$PHASE" = stage ]; then
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  head -2 /etc/os-release; nproc
  mkdir -p /tmp/stage /tmp/syslib
  cp .gpu/p1/site.tar.xz.part-aa /tmp/stage/ || exit 1
  untar_xz /tmp/syslib <.gpu/p1/syslib.tar.xz || exit 1
  for lib in /tmp/syslib/*; do  # keep only what the image lacks
    name=$(basename "$lib")
    if ldconfig -p | awk '{print $1}' | grep -qx "$name"; then rm -f "$lib"; else echo "carried: $name"; fi
  done
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/gs \
    .gpu/p1/gsplat-*.whl || exit 1
  stamp "building gsplat's CUDA extension in the background (sm_90)"
  cd /tmp && PYTHONPATH=/tmp/gs MAX_JOBS=14 TORCH_CUDA_ARCH_LIST=9.0 setsid nohup bash -c \
    "python3 -c \"from gsplat.cuda._backend import _C; print('gsplat extension loaded:', _C is not None)\";
     echo build exit \$?" >/tmp/gsplat_build.log 2>&1 </dev/null &
  stamp "staged"
  exit 0
fi

[ -f /tmp/stage/site.tar.xz.part-aa ] || { echo "nothing staged: run PHASE=stage first"; exit 2; }
if [ ! -d /tmp/site/gsfix_online ]; then
  mkdir -p /tmp/site
  cat /tmp/stage/site.tar.xz.part-aa .gpu/p2/site.tar.xz.part-ab | untar_xz /tmp/site || exit 1
fi
# wheels carried beside part ab (e.g. pyinstrument for PROFILE=1) join the site
for whl in .gpu/p2/*.whl; do
  [ -f "$whl" ] && python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --upgrade --target /tmp/site "$whl"
done
# the checkout's code over the packed wheel's (the wheel maps nodes/ and configs/ into the package)
cp -r gsfix_online/. /tmp/site/gsfix_online/ && cp -r nodes/. /tmp/site/gsfix_online/nodes/ \
  && cp -r configs/. /tmp/site/gsfix_online/configs/ || exit 1
# Open3D imports its plotly drawing and its ML datasets eagerly, and plotly, dash and addict are
# not in the image: make those imports optional (the project uses neither)
python3 - <<'PY'
def optional(path, starts):
    lines = open(path).read().split("\n")
    out = [f"try:\n    {l}\nexcept ImportError:\n    pass" if l.startswith(starts) else l for l in lines]
    open(path, "w").write("\n".join(out))
optional("/tmp/site/open3d/visualization/__init__.py", ("from .draw_plotly", "from .to_mitsuba"))
optional("/tmp/site/open3d/__init__.py", ("import open3d.ml",))
PY
export PYTHONPATH=/tmp/site:/tmp/gs LD_LIBRARY_PATH=/tmp/syslib
# the build flags of the staged extension: torch rebuilds it (90 s, inside the demo's mapping)
# when a process loads it with other -gencode flags than it was built with
export TORCH_CUDA_ARCH_LIST=9.0
stamp "site unpacked"
mkdir -p /tmp/run && cd /tmp/run || exit 1  # not the checkout: its gsfix_online has no nodes/
python3 -c "
import open3d, zmq, diffusers, kornia, torch, numpy, gsfix_online.nodes.splat
print('open3d', open3d.__version__, 'torch', torch.__version__, 'cuda', torch.cuda.is_available(),
      'numpy', numpy.__version__, 'diffusers', diffusers.__version__)" || exit 1
for _ in $(seq 30); do
  grep -q "build exit" /tmp/gsplat_build.log && break
  stamp "waiting for gsplat's CUDA extension to finish building"
  sleep 10
done
tail -3 /tmp/gsplat_build.log

stamp "the demo"
mkdir -p /tmp/run && cd /tmp/run || exit 1
# PROFILE=1: every node's call tree (work/profile/NODE.txt, in demo.tar.gz) to find what the GPU
# leaves on the CPU (on the H200 the splat node's per-frame mapping barely sped up)
rm -rf /tmp/run/demo  # a second call on a warm machine: DEMO_ARGS, e.g. trainer.fixer.train.seed=1
# shellcheck disable=SC2086  # DEMO_ARGS is a list of overrides
timeout "${DEMO_LIMIT_S:-420}" python3 -m gsfix_online.apps.cli demo --out /tmp/run/demo \
  --no-progress ${PROFILE:+--profile} ${DEMO_ARGS:-}
stamp "demo exit $?"
cd /tmp/run/demo && tar -cf - summary.json config.yaml figure.png repair/metrics.json \
  repair/timeline.json repair/timeline.png repair/report.html repair/work/graph.log \
  repair/work/graph.yaml $(ls repair/work/profile/*.txt 2>/dev/null) | gzip -6 >"$OUT/demo.tar.gz"
tar -cf "$OUT/views.tar" repair/views
[ "$(stat -c %s "$OUT/views.tar")" -lt 16000000 ] || rm -f "$OUT/views.tar"
nvidia-smi --query-gpu=name,memory.used --format=csv

cd "$REPO" || exit 1
stamp "GPU tests"
PYTHONPATH=/tmp/site:/tmp/gs:$REPO python3 -m pytest -q -p no:cacheprovider -m gpu \
  tests/mapping/splat/test_render_cpu.py tests/mapping/splat/test_mapper.py
[ -n "${SKIP_BENCH:-}" ] && { stamp "done"; exit 0; }
stamp "render speed: gsplat against the CPU rasterizer"
PYTHONPATH=/tmp/site:/tmp/gs:$REPO python3 benchmarks/bench_cuda.py --sections render --repeats 5 \
  --out "$OUT/cuda_render.json"
stamp "GSFixer speed: the shipped base"
PYTHONPATH=/tmp/site:/tmp/gs:$REPO python3 benchmarks/bench_cuda.py --sections fixer --repeats 3 \
  --cpu-threads 0 --base gsfix_online/fixer/weights/base --out "$OUT/cuda_fixer.json"
stamp "done"
