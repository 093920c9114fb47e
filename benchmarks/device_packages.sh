#!/usr/bin/env bash
# The packages benchmarks/device_demo.sh carries to a lent GPU machine, made here (about 4 min on
# 2 cores): .gpu/p1 (gsplat's wheel, syslib.tar.xz, site.tar.xz.part-aa) and .gpu/p2
# (site.tar.xz.part-ab), each small enough to travel beside the tree (64 MiB a call).
# The machine's image has Python 3.12, torch, numpy, OpenCV (the plain build), transformers and
# no registry access; site.tar.xz holds what it lacks: this project's wheel, Open3D's CPU wheel
# without its examples and lighting assets, diffusers, kornia, pyzmq, the MCAP and rosbag readers,
# plyfile, trimesh. syslib.tar.xz holds the X11/GL/udev libraries Open3D links (the run keeps
# only those the image lacks). Versions: this checkout's .venv's, for Python 3.12.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
grep -qx '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >>.git/info/exclude
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
version() { $PY -c "import importlib.metadata as m; print(m.version('$1'))"; }
platforms=""
for n in 39 35 34 31 28 27 24 17; do platforms="$platforms --platform manylinux_2_${n}_x86_64"; done
fetch() {  # NAME==VERSION ... as Python 3.12 wheels, into $tmp/whl
  # shellcheck disable=SC2086  # platforms is a list of options
  $PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    $platforms --platform manylinux2014_x86_64 -d "$tmp/whl" "$@"
}
echo "downloading the wheels the GPU image lacks"
for p in diffusers kornia kornia_rs plyfile gsplat pyzmq rosbags lz4 ruamel.yaml zstandard mcap \
  mcap-protobuf-support foxglove-schemas-protobuf trimesh importlib_metadata; do
  fetch "$p==$(version "$p")"
done
fetch open3d-cpu==0.19.0  # manylinux_2_31: the image's glibc is 2.39
$PY -m pip wheel -q --no-deps --no-build-isolation . -w "$tmp/whl"
echo "unpacking them into one site tree"
mkdir -p "$tmp/site"
for w in "$tmp"/whl/*.whl; do
  case $w in *gsplat-*) continue ;; esac  # installed apart: its CUDA build starts in the first call
  unzip -q -o "$w" -d "$tmp/site"
done
rm -rf "$tmp/site/open3d/examples" "$tmp/site/open3d/resources/"*.ktx "$tmp/site/open3d/cpu/open3d_torch_ops.so"
echo "packing (xz)"
tar -cf - -C "$tmp/site" . | xz -T0 -8 >"$tmp/site.tar.xz"
mkdir -p "$tmp/syslib"
for l in libX11.so.6 libxcb.so.1 libXau.so.6 libXdmcp.so.6 libbsd.so.0 libmd.so.0 libudev.so.1 \
  libGL.so.1 libGLX.so.0 libGLdispatch.so.0 libgomp.so.1; do
  cp -L "/lib/x86_64-linux-gnu/$l" "$tmp/syslib/"
done
rm -rf .gpu/p1 .gpu/p2
mkdir -p .gpu/p1 .gpu/p2
cp "$tmp"/whl/gsplat-*.whl .gpu/p1/
tar -cJf .gpu/p1/syslib.tar.xz -C "$tmp/syslib" .
head -c 25000000 "$tmp/site.tar.xz" >.gpu/p1/site.tar.xz.part-aa
tail -c +25000001 "$tmp/site.tar.xz" >.gpu/p2/site.tar.xz.part-ab
du -b .gpu/p1 .gpu/p2
