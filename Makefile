# Quick start: `make demo` then `make test`. Both are idempotent.
VENV    ?= .venv
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
OUT     ?= outputs/demo
# CPU machines pin the CPU wheel; a GPU install sets TORCH_SPEC to its CUDA build (see README).
TORCH_SPEC ?= torch==2.13.0
SYS_PKGS := libusb-1.0-0 libgl1 libgomp1
# the viewer and report browser tests (headless, through selenium)
TEST_PKGS := chromium chromium-driver

.PHONY: setup sys-deps test-deps demo test lint docs viewer-png bench pretrain pretrain-stage2 clean

setup: $(STAMP)

# install the Debian packages named in $(1) that are missing (as root), else name them
define apt_install
	@missing=""; for p in $(1); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	    echo "installing system packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	  else echo "missing system packages:$$missing (install them with: sudo apt-get install$$missing)"; exit 1; fi; \
	fi
endef

sys-deps:
	$(call apt_install,$(SYS_PKGS))

test-deps:
	$(call apt_install,$(TEST_PKGS))

$(STAMP): pyproject.toml | sys-deps
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q $(TORCH_SPEC)
# the plain OpenCV builds share cv2's files with the contrib build we need: remove them first
	$(PY) -m pip uninstall -y -q opencv-python-headless opencv-python 2>/dev/null || true
	$(PY) -m pip install -q -e '.[dev,docs,sensors,viewer,cuda]'
# with a CUDA build of torch and a GPU, compile gsplat's kernels now, not inside the first run's
# mapping (benchmarks/results/demo_h200_three_seeds.md: 90 s of its Gaussian map's time)
	@if $(PY) -c "import sys, torch; sys.exit(not torch.cuda.is_available())"; then \
	  echo "compiling gsplat's CUDA kernels (once, about 90 s)"; \
	  $(PY) -c "from gsplat.cuda._backend import _C; assert _C is not None, 'gsplat CUDA build failed'"; \
	fi
	touch $(STAMP)

demo: setup
	$(VENV)/bin/gsfix-online demo --out $(OUT)

# two pytest-xdist workers; tests/conftest.py says which tests share a worker and which run
# one after another; PYTEST_WORKERS=0 runs the suite in this process
PYTEST_WORKERS ?= 2
test: setup test-deps
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile -m "not gpu and not device" tests

# (make test runs the import-linter contracts too: tests/test_architecture.py)
lint: setup
	$(VENV)/bin/ruff check gsfix_online nodes tests benchmarks
	$(VENV)/bin/ruff format --check gsfix_online nodes tests benchmarks
	$(VENV)/bin/lint-imports

# the documentation site into site/ (open site/index.html); make test builds it with --strict
docs: setup
	$(VENV)/bin/mkdocs build --strict --site-dir site

# docs/viewer.png: the viewer's first picture, taken by the browser test on its run
viewer-png: setup test-deps
	GSFIX_VIEWER_SCREENSHOT=$(CURDIR)/docs/viewer.png $(PY) -m pytest -q tests/apps/test_browser.py -k opens_on_the_map

bench: setup
	$(PY) benchmarks/bench_readers.py
	$(PY) benchmarks/bench_transport.py
	flock /tmp/gsfix-bench.lock $(PY) benchmarks/bench_fixer.py
	$(PY) benchmarks/bench_tsdf.py
	flock /tmp/gsfix-bench.lock $(PY) benchmarks/bench_render.py
	flock /tmp/gsfix-bench.lock $(PY) benchmarks/bench_mapping.py

# The GSFixer base checkpoint (~80 min on 2 cores extrapolated, resumable; 200 s on an H200): outputs/fixer_pretrain/base.
pretrain: setup
	flock /tmp/gsfix-bench.lock $(VENV)/bin/gsfix-online fixer pretrain --out outputs/fixer_pretrain --resume

# Its second stage on our own maps, what ships (benchmarks/results/base_maps_cpu.md): map triplets
# of 100 scenes (25 min on 2 cores one at a time, cached; maps.workers=2 builds two at once),
# then 30 min of training: outputs/fixer_stage2/base.
pretrain-stage2: setup
	flock /tmp/gsfix-bench.lock $(VENV)/bin/gsfix-online fixer pretrain --out outputs/fixer_stage2 \
	  --resume pretrain.init=outputs/fixer_pretrain/base pretrain.scenes=100 pretrain.val_scenes=6 \
	  pretrain.variants=4 pretrain.maps.views=8 pretrain.maps.workers=2 pretrain.steps=1000000 \
	  pretrain.time_limit_s=1800 \
	  pretrain.eval_every=250 pretrain.save_every=500 pretrain.train.lr=1e-4 \
	  pretrain.train.batch_size=32 pretrain.train.grad_accum=1 pretrain.train.crop=32 \
	  pretrain.train.ema_decay=0.999 fixer.masks.p_shared=0.5 fixer.masks.p_gs_only=0.5

clean:
	rm -rf outputs .pytest_cache site
