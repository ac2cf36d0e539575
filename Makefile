# Two commands do everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_OUT ?= build/demo

.PHONY: install demo test clean

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

clean:
	rm -rf $(VENV) build .pytest_cache
