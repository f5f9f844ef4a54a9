# Two commands do all the set-up on a fresh machine:
#   make run   - create .venv, install slam2d[web,viz], and start the web lab (prints the URL; Ctrl+C stops it;
#                PORT=8010 serves on another port)
#   make demo  - every estimator on the default scenario: a table and out/demo.png
#   make test  - create .venv, install test dependencies, lint, type-check and run the test suite
#   make test-long - the same plus the long tests (whole real logs, 30-run Monte Carlo: SLAM2D_LONG_TESTS=1)
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)

.PHONY: run demo chromium test test-long lint typecheck pytest bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e ".[dev,viz,web,cluster,crosscheck]"
	rm -f $(VENV)/.installed-*
	touch $(STAMP)

# serving the lab needs only the web and viz extras (not the test tools): its own stamp, so `make run` on a fresh
# clone installs a small environment; PORT=8010 picks another port
PORT ?= 8000
RUN_STAMP := $(VENV)/.installed-run-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)

$(RUN_STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e ".[web,viz]"
	rm -f $(VENV)/.installed-run-*
	touch $(RUN_STAMP)

# one BLAS thread: the lab's matrices are small, and BLAS threads on a busy machine slow a step 20x
run: $(RUN_STAMP)
	@OPENBLAS_NUM_THREADS=$${OPENBLAS_NUM_THREADS:-1} $(VENV)/bin/slam2d lab --port $(PORT)

demo: $(STAMP)
	$(VENV)/bin/slam2d demo --out out

# browser tests drive Debian's chromium (never `playwright install`); install it when missing (we run as root)
chromium:
	@command -v chromium >/dev/null || (apt-get update && apt-get install -y chromium) || echo "chromium could not be installed: browser tests will be skipped"

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests $(wildcard benchmarks tools)
	$(VENV)/bin/lint-imports

typecheck: $(STAMP)
	$(VENV)/bin/mypy

# two workers (pytest-xdist; each test file stays on one worker, so its module fixtures are built once): the suite
# takes about half the wall time on the 2-core CI machine; PYTEST_WORKERS=0 runs it in one process
PYTEST_WORKERS ?= 2
pytest: $(STAMP) chromium
	OPENBLAS_NUM_THREADS=$${OPENBLAS_NUM_THREADS:-1} $(PY) -m pytest -n $(PYTEST_WORKERS) --dist loadfile --durations=25

test: lint typecheck pytest

# the long tests (tests/testkit.py LONG) beside the rest: an hour or more on the 2-core CI machine (the three
# MRCLAM multi-robot runs take 15-25 min each)
test-long:
	SLAM2D_LONG_TESTS=1 $(MAKE) test

bench: $(STAMP)
	@for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) out .pytest_cache .mypy_cache .ruff_cache
