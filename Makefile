# frfcal: `make demo` and `make test` work from a fresh clone.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
EXTRAS ?= dev,visa,ni,dask
STAMP  := $(VENV)/.installed-$(shell echo $(EXTRAS) | tr ',' '-')

.PHONY: test test-all demo bench lint clean venv

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[$(EXTRAS)]"
	@# CHOLMOD (scikit-sparse) makes modes ~2x faster; it needs libsuitesparse-dev.
	@# Without it femodel falls back to SuperLU, so a failed build is not an error.
	-$(PY) -m pip install --quiet "scikit-sparse>=0.4.12,<0.5" 2>/dev/null || echo "note: scikit-sparse not installed (apt-get install libsuitesparse-dev to enable CHOLMOD)"
	touch $@

lint: $(STAMP)
	$(VENV)/bin/lint-imports

test: $(STAMP) lint
	$(PY) -m pytest -q -m "not slow and not hardware"

test-all: $(STAMP) lint
	$(PY) -m pytest -q -m "not hardware"

demo: $(STAMP)
	$(PY) -m frfcal demo --out demo-output

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) demo-output .pytest_cache build *.egg-info
