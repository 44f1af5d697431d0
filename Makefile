# Two commands on a fresh machine: `make run` and `make test`. Everything installs into .venv.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

# glibc returns freed memory to the OS eagerly and re-faults it on the next allocation; on these
# machines that costs 2-4x in torch code (DESIGN section 7). Keeping it mapped avoids the faults.
export MALLOC_MMAP_THRESHOLD_ := 34359738368
export MALLOC_TRIM_THRESHOLD_ := 34359738368
export THP_MEM_ALLOC_ENABLE := 1

.PHONY: install run demo test bench bench-prior data clean

install: $(STAMP)

# torch is pinned and installed first on its own, so pip takes the local CPU wheel; the project is
# installed without build isolation (an isolated build would pull a multi-GB CUDA torch); then the
# fused hash-grid kernel is compiled once into its on-disk cache.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip setuptools wheel
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet --no-build-isolation -e '.[test]'
	$(BIN)/python -m model.nerf.encodings.kernels
	touch $(STAMP)

run: demo

demo: install
	$(BIN)/hypnerf demo --out runs/demo

test: install
	$(BIN)/python -m pytest -q

bench: install
	$(BIN)/pip install --quiet --no-deps nerfstudio==1.1.5 jaxtyping wadler_lindig rich viser msgspec websockets zstandard
	$(BIN)/pip install --quiet 'matplotlib>=3.8'
	$(BIN)/python -m benchmarks.run_all

# The category prior (hours on 2 cores): dataset with colour variants, training, compression,
# ablation, disentanglement, then the hypernetwork presets compared. Stages already done are
# skipped; training resumes where it stopped.
bench-prior: install
	$(BIN)/pip install --quiet 'matplotlib>=3.8'
	$(BIN)/python -m benchmarks.bench_prior
	$(BIN)/python -m benchmarks.bench_presets
	$(BIN)/python -m benchmarks.report

data: install
	$(BIN)/hypnerf data synth --out data/synth --objects 16 --views 91 --res 128 --seed 0
	$(BIN)/hypnerf data import-sh3d --out data/sh3d-chair --category chair --views 91 --res 128

clean:
	rm -rf $(VENV) runs build *.egg-info
