# Two commands do all set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Idle OpenMP threads sleep instead of spinning: on a shared 2-core machine spinning threads slow torch 5-50x.
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: install demo test bench lint docs clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# The CPU wheel these machines hold; a bare `torch` would pull a multi-GB CUDA build.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[io,viz,video,fast,dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/evseg demo --out demo_out

test: $(STAMP)
	$(PY) -m pytest -p no:cacheprovider --doctest-modules --nbmake --nbmake-timeout=600 evseg_torch tests notebooks $(PYTEST_ARGS)

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

# The README's figures, from the commands printed under them.
docs: $(STAMP)
	$(PY) docs/make_figures.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check evseg_torch tests benchmarks

clean:
	rm -rf $(VENV) demo_out *.egg-info
