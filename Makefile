# Two commands do everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_OUT ?= build/demo

.PHONY: install demo test images images-cuda clean

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[dev]'
	touch $(STAMP)

# Compresses the bundled 256x256 sample material with the quick `fast` schedule (about 10 s on 2 CPU cores),
# prints its report, then decodes mip 0 back to images.
demo: $(STAMP)
	$(BIN)/bcf compress examples/sample -o $(DEMO_OUT)/sample --preset fast --force
	$(BIN)/bcf decode $(DEMO_OUT)/sample -o $(DEMO_OUT)/sample_decoded

# One torch thread per test worker: two workers with two threads each on a 2-core machine made training
# steps up to 20x slower (threads spin-waiting on each other), and `bcf` subprocesses inherit the setting.
test: $(STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -n 2 tests

# Builds the CPU image from docker/Dockerfile with buildah (no Docker daemon needed) and runs it: bcf --version,
# a fast compress of the sample, and one job through Redis, the API and a worker (docker/README.md); as root.
images:
	docker/check_image.sh cpu

# The same for docker/Dockerfile.cuda (a GPU-less check: the CUDA build of torch, run on the CPU); several GB.
images-cuda:
	docker/check_image.sh cuda

clean:
	rm -rf $(VENV) build .pytest_cache
