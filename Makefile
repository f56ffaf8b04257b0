# Two commands for a fresh machine with python3 and make:  `make demo`  and  `make test`.
PYTHON ?= python3
VENV   ?= .venv
PIP    := $(VENV)/bin/pip
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# Keeps pip from resolving torch to a CUDA build: every install goes through the constraints.
PIPC   := $(PIP) install --disable-pip-version-check -q -c constraints.txt

.PHONY: demo test venv bench clean lint-docker
venv: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIPC) --upgrade pip setuptools wheel
	$(PIPC) torch==2.13.0
	$(PIPC) -e '.[dev]'
	touch $@

demo: $(STAMP)
	$(VENV)/bin/lightfield demo

# The linter first (ruff, configured in pyproject.toml: a few seconds), then the suite.
# PASSIVE: idle OpenMP threads sleep instead of spinning, so the test suite's subprocesses
# (Celery workers, uvicorn) do not starve each other on a 2-core machine.
test: $(STAMP)
	$(VENV)/bin/ruff check .
	OMP_WAIT_POLICY=PASSIVE $(PY) -m pytest -q

bench: $(STAMP)
	$(VENV)/bin/lightfield bench --quick -o bench/results

clean:
	rm -rf $(VENV) lightfield-data demo-output
