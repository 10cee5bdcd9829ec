# poseflow: the two set-up commands are `make demo` and `make test`; both build .venv themselves.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# One thread, the command line's own default (`poseflow COMMAND --help`, --threads): more threads
# are slower while another process uses the cores. On free cores: make ... OMP_NUM_THREADS=N
export OMP_NUM_THREADS ?= 1

.PHONY: demo demo-validity test test-slow lint docs docs-serve docs-pictures bench bench-unseen bench-quick venv sysdeps clean wheel-check

sysdeps:
	@$(PYTHON) -c "import ctypes.util,sys; sys.exit(0 if all(ctypes.util.find_library(l) for l in ('usb-1.0','GL','EGL')) else 1)" \
	  || { (apt-get update -qq && apt-get install -y -qq libusb-1.0-0 libgl1 libegl1 libgomp1) >/dev/null \
	  || echo "warning: could not install libusb-1.0-0/libgl1/libegl1; open3d may fail to import"; }

$(STAMP): pyproject.toml
	$(MAKE) sysdeps
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q -m "not slow" -p no:cacheprovider

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow -p no:cacheprovider || [ $$? -eq 5 ]

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# The API reference and guides (mkdocs.yml, docs/) into site/; offline, any warning fails it.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

# The guides' pictures (docs/images/): an overlay and the timing chart of a fresh demo run.
docs-pictures: $(STAMP)
	rm -rf build/pictures && $(VENV)/bin/poseflow demo --images 2 --out build/pictures -q
	mkdir -p docs/images
	cp "$$(ls build/pictures/overlays/*.png | head -n 1)" docs/images/demo_overlay.png
	cp build/pictures/timing.png docs/images/demo_timing.png

# What `valid` means for the shipped demo model (src/poseflow/assets/demo_model/validity.json):
# calibrated on 80 renders of the demo objects, one per layout, with a seed no training used.
demo-validity: $(STAMP)
	rm -rf build/demo_validity
	$(VENV)/bin/poseflow synth build/demo_validity/renders --train 0 --test 80 --seed 11 --images-per-scene 1 -q
	$(VENV)/bin/poseflow calibrate build/demo_validity/renders --model src/poseflow/assets/demo_model --work build/demo_validity --cache build/demo_validity/cache

# The built site at http://localhost:8000 (search runs in a web worker, which browsers refuse to
# start from a file:// page; pages, links and pictures also work opened as files).
docs-serve: docs
	$(PY) -m http.server 8000 --bind 127.0.0.1 --directory site

BENCHMARKS := registration data networks features eval accuracy pipeline ablation threads demo_threads

bench: $(STAMP)
	for b in $(BENCHMARKS); do $(PY) benchmarks/$$b.py || exit 1; done

# The README recipe on a user's BOP folder: make bench-unseen DATASET=path/to/bop_dataset
bench-unseen: $(STAMP)
	@test -n "$(DATASET)" || { echo "usage: make bench-unseen DATASET=path/to/bop_dataset"; exit 2; }
	$(PY) benchmarks/unseen.py $(DATASET)

# gpu.py needs a GPU at full scale (benchmarks/RESULTS.md gives its commands); --quick is its CPU dry run
bench-quick: $(STAMP)
	for b in $(BENCHMARKS) unseen detection diagnose conditioning_use gpu surface_precision other_renderer validity; do $(PY) benchmarks/$$b.py --quick || exit 1; done

demo: $(STAMP)
	$(PY) -m poseflow.cli demo

# A user's first run from the built wheel alone: a fresh venv with torch and the wheel (its
# dependencies from the registry, no extras), then the demo and `poseflow estimate` on a
# generated frame, run outside the source tree (in build/wheel-check).
WHEEL_DIR := build/wheel-check
FRAME := frame/test/000000

wheel-check:
	$(MAKE) sysdeps
	rm -rf dist $(WHEEL_DIR)
	$(PYTHON) -m pip wheel -q --no-deps -w dist .
	$(PYTHON) -m venv $(WHEEL_DIR)/venv
	$(WHEEL_DIR)/venv/bin/python -m pip install -q torch==2.13.0
	$(WHEEL_DIR)/venv/bin/python -m pip install -q dist/poseflow-*.whl
	cd $(WHEEL_DIR) && venv/bin/poseflow demo --images 2 --out demo --no-progress
	cd $(WHEEL_DIR) && venv/bin/poseflow synth frame --train 0 --test 1 --objects-per-image 1 \
	  --width 320 --height 240 --no-progress
	cd $(WHEEL_DIR) && venv/bin/poseflow estimate --rgb $(FRAME)/rgb/000000.png \
	  --depth $(FRAME)/depth/000000.png --K $(FRAME)/scene_camera.json \
	  --mask $(FRAME)/mask_visib/000000_000000.png --mesh frame/models \
	  --obj-id $$(venv/bin/python -c "import json; print(json.load(open('$(FRAME)/scene_gt.json'))['0'][0]['obj_id'])") \
	  --out estimate --no-progress
	cd $(WHEEL_DIR) && venv/bin/python -c "import json, sys; \
	  p = json.load(open('estimate/poses.json'))['poses']; \
	  sys.exit(0 if len(p) == 1 and p[0]['valid'] else 'poseflow estimate: no valid pose')"

clean:
	rm -rf $(VENV) build dist site src/*.egg-info
