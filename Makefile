# The two commands of the README: `make demo` and `make test`. Each sets up everything it needs on a fresh machine:
# the Debian libraries Open3D loads, a virtual environment in .venv, the package and the example plugins.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# Debian packages whose shared libraries the open3d wheel links against (libusb: the RealSense bits; libgl/libgomp:
# rendering and OpenMP).
DEB_LIBS := libusb-1.0-0 libgl1 libgomp1
# Debian's Chromium and its WebDriver: the report's browser test opens a `gdt report` page in headless Chromium
# (tests/test_report_browser.py; it skips, saying why, without them).
BROWSER_DEBS := chromium chromium-driver

.PHONY: demo test setup system-deps browser-deps lint bench clean

demo: setup
	$(BIN)/gdt scene test-scene workflows/data/test_scene --seed 0
	$(BIN)/gdt run workflows/demo.yaml --overwrite
	$(BIN)/gdt audit out/demo_twin

# Two workers (the machines this runs on have two cores), a test module to each at a time: module fixtures are
# built once, and the bad-input corpus (one module) runs its cases two at a time in one of them.
test: setup browser-deps
	$(BIN)/python -m pytest -q -p no:cacheprovider -n 2 --dist loadscope

bench: setup
	$(BIN)/python bench/speed.py
	$(BIN)/python bench/scale.py
	$(BIN)/python bench/engine_throughput.py
	$(BIN)/python bench/voxel_mle.py
	$(BIN)/python bench/distances.py
	$(BIN)/python bench/rov_depth.py
	$(BIN)/python bench/report.py
	$(BIN)/python bench/append.py
	$(BIN)/python bench/tile_halos.py
	$(BIN)/python bench/tile_reads.py
	$(BIN)/python bench/twin_write.py
	$(BIN)/gdt eval workflows/test_scene.yaml --json out/eval/test_scene/result.json
	$(BIN)/gdt eval workflows/fuselage.yaml --json out/eval/fuselage/result.json

lint: setup
	$(BIN)/ruff check .
	$(BIN)/mypy

setup: system-deps $(STAMP)

# Install only what is missing; apt-get needs root (the CI and developer machines run as root).
system-deps: PKGS := $(DEB_LIBS)
browser-deps: PKGS := $(BROWSER_DEBS)
system-deps browser-deps:
	@missing=""; for p in $(PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO="sudo"; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing >/dev/null; \
	fi

$(STAMP): pyproject.toml plugins/gdt-c2c/pyproject.toml plugins/gdt-m3c2/pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[dev,eval,cad,bim]" -e plugins/gdt-c2c -e plugins/gdt-m3c2
	@touch $(STAMP)

clean:
	rm -rf $(VENV) out workflows/data .pytest_cache
