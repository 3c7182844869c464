# Two commands for a fresh machine with Python 3.11:
#   make run   - set up .venv, install facetsynth, run the workflow on the demo sample
#   make test  - set up .venv, install facetsynth with test extras, run the test suite
#   make lint  - ruff (src, tests, scripts), snakefmt --check (Snakefile, rules), snakemake --lint by text (.ci/lint)
#   make test-scenes - the slow whole-workflow tests: the scenes of issue 13 at native resolution, issue 4's
#                synthesis scenes, the demo with its report and exports, the Mitsuba copper at 480 lights
#                (20-24 min on 2 cores; CI runs them after make test, the cluster test beside them)
#   make test-cluster - two samples through a single-node SLURM cluster on localhost against a local run (4-5 min
#                alone; installs Debian's slurmctld, slurmd, slurm-client and munge when missing: needs root)
#   make bench - run every preset (fast, balanced, accurate) on demo, wallpaper, satin (native: 168^2) and
#                paper-256 (the paper-scale scene and lights, 256^2 native) and write results/bench/tradeoff.csv
#                and tradeoff.png (about 25 min on 2 cores); restrict with
#                make bench BENCH_PRESETS=fast BENCH_SCENES=demo, or BENCH_ARGS=--dry-run
#   make bench-scale - time, memory and disk per stage against the points (64^2 ... 800^2 at 480 frames) and
#                the frames (120 ... 2600 at 128^2): results/bench/scale.csv and scale.png (about 35 min; each
#                run's frames and tables are deleted once its figures are recorded: 800^2 writes ~22 GB);
#                restrict with make bench-scale SCALE_ARGS="--points 64 128 256 --frames 120 480"
#   make bench-real - facetsynth against the per-pixel fits RTI users rely on (Lambert, PTM, HSH2, HSH3; HSH3
#                fitted to the 8-bit codes too, as RTIBuilder and relight fit it) on the
#                real light-dome photos of config/samples-rti.tsv (read from ../shared/data/rti, never copied):
#                relative L2 on the fitting and held-out lights, fit time and memory in
#                results/bench-real/table.md and table.csv (about 17 min on 2 cores; not run by CI);
#                restrict with make bench-real REAL_ARGS="--captures rti-leaf"

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
CORES ?= 2
BENCH_PRESETS ?= fast balanced accurate
BENCH_SCENES ?= demo wallpaper satin paper-256
BENCH_ARGS ?=
SCALE_ARGS ?=
REAL_ARGS ?=

.PHONY: run lint test test-scenes test-cluster test-firmware bench bench-scale bench-real clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(VENV)/.installed-run: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $@ $(VENV)/.installed-run

$(VENV)/.installed-cluster: pyproject.toml $(VENV)/.installed-test
	$(BIN)/python -m pip install --quiet -e ".[test,cluster]"
	touch $@

run: $(VENV)/.installed-run
	$(BIN)/snakemake --cores $(CORES)

test: $(VENV)/.installed-test
	$(BIN)/python -m pytest -q -n $(CORES) --dist loadfile

lint: $(VENV)/.installed-test
	BIN=$(BIN) .ci/lint

test-scenes: $(VENV)/.installed-test
	$(BIN)/python -m pytest -q -m scenes -n $(CORES) --dist loadfile

test-cluster: $(VENV)/.installed-cluster
	bash tests/cluster/install.sh
	$(BIN)/python -m pytest -q -m cluster

test-firmware: $(VENV)/.installed-test
	bash rig/firmware/install-toolchain.sh
	$(MAKE) -C rig/firmware BUILD_DIR=$(CURDIR)/.firmware-build
	$(BIN)/python -m pytest -q -m 'not scenes and not cluster' tests/rig/test_rig_conformance.py

bench: $(VENV)/.installed-run
	$(BIN)/python workflow/scripts/bench.py --cores $(CORES) --presets $(BENCH_PRESETS) --scenes $(BENCH_SCENES) $(BENCH_ARGS)

bench-scale: $(VENV)/.installed-run
	$(BIN)/python workflow/scripts/bench_scale.py --cores $(CORES) --prune $(SCALE_ARGS)

bench-real: $(VENV)/.installed-run
	$(BIN)/python workflow/scripts/bench_real.py --cores $(CORES) $(REAL_ARGS)

clean:
	rm -rf results/* .snakemake
