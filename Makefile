# rangefuse: `make run` and `make test` are the two commands; see README.md.
PY ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-dev
BENCH_STAMP := $(VENV)/.installed-bench
PYTEST_FLAGS ?= -q

.PHONY: install run demo test test-real check lint types bench bench-full clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# The REST service with the embedded default store in ./data (the first start creates and
# prints a token): on 127.0.0.1:8000, or `make run PORT=8080 HOST=0.0.0.0`; without them,
# RANGEFUSE_PORT and RANGEFUSE_HOST are read as `rangefuse serve` reads them.
run: install
	$(BIN)/rangefuse serve --data-dir data $(if $(HOST),--host $(HOST)) $(if $(PORT),--port $(PORT))

demo: install
	$(BIN)/rangefuse synth object out/demo-object --views 12
	$(BIN)/rangefuse fuse out/demo-object --voxel-size 0.012 --mode closed \
		--max-discontinuity 0.05 --grid-out out/demo-object-grid.npz -o out/demo-object.ply

test: install
	$(BIN)/pytest $(PYTEST_FLAGS) -m "not real_data"

# Tests on real scanner data (the Stanford bunny) read from ../shared/data; they fail here,
# not skip, when the data are missing.
SHARED_DATA ?= $(CURDIR)/../shared/data
test-real: install
	@test -f "$(SHARED_DATA)/stanford-bunny/scans/bun.conf" || { \
		echo "make test-real: the real data are missing: no $(SHARED_DATA)/stanford-bunny/scans/bun.conf" \
			"(the real-data tests read ../shared/data; see tests/test_bunny.py)" >&2; exit 1; }
	RANGEFUSE_SHARED_DATA="$(SHARED_DATA)" $(BIN)/pytest $(PYTEST_FLAGS) -m real_data

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# mypy cannot see through the editable install's import hook (the installed names are
# rangefuse.engine, ...): it reads the packages through a tree of links under build/.
TYPES_TREE := build/typecheck/rangefuse
types: install
	@mkdir -p $(TYPES_TREE)
	@for p in engine storage service; do ln -sfn ../../../$$p $(TYPES_TREE)/$$p; done
	MYPYPATH=build/typecheck $(BIN)/mypy -p rangefuse.engine -p rangefuse.storage -p rangefuse.service

check: lint types test

$(BENCH_STAMP): $(STAMP)
	@# Open3D's wheel links libusb; install it from Debian when missing (needs root).
	@if ! ldconfig -p | grep -q libusb-1.0.so.0; then \
		if [ "$$(id -u)" = 0 ]; then apt-get install -y -q libusb-1.0-0 >/dev/null \
			|| (apt-get update -q && apt-get install -y -q libusb-1.0-0 >/dev/null); \
		else echo "open3d needs libusb-1.0-0: sudo apt-get install libusb-1.0-0"; exit 1; fi; \
	fi
	$(BIN)/python -m pip install -q -e '.[dev,bench]'
	touch $(BENCH_STAMP)

# Small inputs: a smoke run of every benchmark.
bench: $(BENCH_STAMP)
	$(BIN)/python benchmarks/fusion.py --quick
	$(BIN)/python benchmarks/meshing.py --quick
	$(BIN)/python benchmarks/out_of_core.py --quick
	$(BIN)/python benchmarks/vs_open3d.py --quick

# The sizes the issues report.
bench-full: $(BENCH_STAMP)
	$(BIN)/python benchmarks/fusion.py
	$(BIN)/python benchmarks/meshing.py
	$(BIN)/python benchmarks/out_of_core.py
	$(BIN)/python benchmarks/vs_open3d.py

clean:
	rm -rf $(VENV) .numba_cache out build .pytest_cache .mypy_cache .ruff_cache

# Containers (docs/deployment.md). test-docker: starts dockerd when none runs, builds the image
# (on a base built from Debian packages when Docker Hub cannot be reached), then runs the
# compose stack end to end with one worker killed mid-job (docker/test-docker.sh).
.PHONY: docker-base docker-image test-docker
DOCKER_IMAGE ?= rangefuse:latest
docker-base:
	docker/base/build.sh rangefuse-base:bookworm

docker-image:
	RANGEFUSE_IMAGE=$(DOCKER_IMAGE) PY=$(BIN)/python docker/test-docker.sh build

test-docker: install
	RANGEFUSE_IMAGE=$(DOCKER_IMAGE) PY=$(BIN)/python docker/test-docker.sh all
