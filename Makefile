# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
TORCH_VERSION ?= 2.13.0
# tcmalloc keeps resident memory flat in the renderer's chunked loops (used only when installed).
TCMALLOC := $(firstword $(wildcard /usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4 /usr/lib/aarch64-linux-gnu/libtcmalloc_minimal.so.4))
RUNENV := $(if $(TCMALLOC),LD_PRELOAD=$(TCMALLOC),)
DEMO_OUT ?= outputs/demo

.PHONY: install test test-all demo bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# pinned and first: an unpinned torch pulls several GB of CUDA packages
	$(PY) -m pip install -q torch==$(TORCH_VERSION)
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

install: $(VENV)/.installed

# Everything but the GPU tests, slow end-to-end runs included (CI runs exactly this), in TEST_JOBS processes of one
# thread each (tests/conftest.py): 1.6x faster than one process on 2 cores.
TEST_JOBS ?= 2
test: install
	$(RUNENV) $(PY) -m pytest -q -m "not gpu" -n $(TEST_JOBS)

test-all: install
	$(RUNENV) $(PY) -m pytest -q

demo: install
	$(RUNENV) $(PY) -m realityavatar.train +experiment=demo hydra.run.dir=$(DEMO_OUT)

bench: install
	$(RUNENV) $(PY) benchmarks/render.py
	$(RUNENV) $(PY) benchmarks/scene.py

clean:
	rm -rf $(VENV) outputs
