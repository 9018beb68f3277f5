# Two commands do all set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Idle OpenMP threads sleep instead of spinning: on a shared 2-core machine spinning threads slow torch 5-50x.
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: install demo test test-torch bench lint docs figures clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# The CPU wheel these machines hold; a bare `torch` would pull a multi-GB CUDA build.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[io,viz,video,fast,dev,docs]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/evseg demo --out demo_out

test: $(STAMP)
	$(PY) -m pytest -p no:cacheprovider --doctest-modules --nbmake --nbmake-timeout=600 evseg_torch tests notebooks $(PYTEST_ARGS)

# Level two and the pipeline once more on the tensor and NumPy code alone (no compiled kernel): the path
# of a machine without Numba, and of a GPU (evseg_torch.backend).
test-torch: $(STAMP)
	EVSEG_BACKEND=torch $(PY) -m pytest -p no:cacheprovider -q tests/level_two tests/kernels tests/graphcut tests/test_pipeline.py $(PYTEST_ARGS)

# The commands of docs/benchmarks.md, each one's output in docs/_build/benchmarks/ (over an hour).
bench: $(STAMP)
	$(PY) benchmarks/run_docs_commands.py

# The documentation with the API reference, from the docstrings: docs/_build/html/index.html.
docs: $(STAMP)
	$(PY) -m sphinx -W --keep-going -b html -q docs docs/_build/html

# The README's figures, from the commands printed under them.
figures: $(STAMP)
	$(PY) docs/make_figures.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check evseg_torch tests benchmarks

clean:
	rm -rf $(VENV) demo_out *.egg-info docs/_build docs/api
