# frfcal: `make demo` and `make test` work from a fresh clone.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
EXTRAS ?= dev,visa,ni,dask,fast
# scikit-sparse is built only when this header exists (make SUITESPARSE_INCLUDE= to skip it)
SUITESPARSE_INCLUDE ?= /usr/include/suitesparse
STAMP  := $(VENV)/.installed-$(shell echo $(EXTRAS) | tr ',' '-')

.PHONY: test test-heavy test-all test-fallback demo bench lint clean venv

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[$(EXTRAS)]"
	@# The 'fast' extra (cholespy: CHOLMOD in a pip wheel) needs nothing from the system.
	@# scikit-sparse (CHOLMOD on the system BLAS, fastest) builds only against SuiteSparse
	@# headers (Debian libsuitesparse-dev): tried only where they are installed.
	@if [ -f "$(SUITESPARSE_INCLUDE)/cholmod.h" ]; then \
	  $(PY) -m pip install --quiet "scikit-sparse>=0.4.12,<0.5" || echo "note: scikit-sparse did not build; using the 'fast' backend"; fi
	touch $@

lint: $(STAMP)
	$(VENV)/bin/lint-imports

test: $(STAMP) lint
	$(PY) -m pytest -q -m "not slow and not heavy and not hardware"

# The whole-chain and diagnosis evidence whose campaign fixtures take 30-60 s each (CI runs it after `make test`).
test-heavy: $(STAMP)
	$(PY) -m pytest -q -m "heavy and not slow and not hardware"

# The SciPy-only path (SuperLU), with the fast backends installed but blocked.
test-fallback: $(STAMP)
	FRFCAL_SPARSE_BACKEND=superlu $(PY) -m pytest -q -m "not slow and not hardware" tests/femodel tests/calibration

test-all: $(STAMP) lint
	$(PY) -m pytest -q -m "not hardware"

demo: $(STAMP)
	$(PY) -m frfcal demo --out demo-output

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) demo-output .pytest_cache build *.egg-info
