# The two commands the README promises, and what serves them. Everything installs into .venv.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test venv kernels bench lint typecheck clean parts

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP) kernels

# the compare path's numba kernels compiled ahead of time into the user's cache folder (cell/analysis/kernels.py):
# a fresh `cell compare` then starts without numba. Rebuilt when the kernels change; without gcc, numba's jit runs
# (and tests/test_analysis_kernels.py skips), except under CELL_REQUIRE_KERNELS=1 (CI, .ci/run): then it fails
kernels: $(STAMP)
	$(PY) -m cell.analysis.kernels || { test "$$CELL_REQUIRE_KERNELS" != 1 && \
		echo "compiled kernels not built (gcc, Python headers?): numba's jit is used"; }

# the Aravis camera driver's Python binding, when the Debian packages it builds against are there (.ci/run)
ARAVIS_STAMP := $(VENV)/.aravis
$(ARAVIS_STAMP): $(STAMP)
	@if pkg-config --exists gobject-introspection-1.0 cairo 2>/dev/null; then \
		$(PY) -m pip install --quiet -e '.[dev,aravis]' && touch $(ARAVIS_STAMP); \
	else echo "Aravis tests will skip: no libgirepository1.0-dev/libcairo2-dev (bash .ci/run installs them)"; fi

demo: $(STAMP) kernels
	$(PY) -m cell demo || test $$? -eq 4  # the demo pillar is dented: its verdict is FAIL (exit 4), as it should be

test: $(STAMP) $(ARAVIS_STAMP) kernels
	$(PY) -m pytest -n 2 --dist loadfile --no-loadscope-reorder -q  # files in tests/conftest.py's order

bench: $(STAMP) kernels
	command -v CloudCompare >/dev/null || (apt-get update && apt-get install -y cloudcompare)  # bench_compare's peer
	$(PY) bench/run_all.py

lint: $(STAMP)
	$(PY) -m ruff check cell drivers fakes tests bench recipes
	$(PY) -m ruff format --check cell drivers fakes tests bench recipes
	$(MAKE) --no-print-directory typecheck

# mypy, configured in pyproject.toml ([tool.mypy]); fakes/conformance.py and drivers/conformance.py make it
# check every device implementation against its Protocol in cell/contracts.py
typecheck: $(STAMP)
	$(PY) -m mypy cell drivers fakes

parts: $(STAMP)
	$(PY) recipes/parts/make_parts.py

clean:
	rm -rf $(VENV) runs .pytest_cache .mypy_cache
