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

.PHONY: install run bundle demo test bench bench-prior bench-models data clean

install: $(STAMP)

# torch is pinned and installed first on its own, so pip takes the local CPU wheel; the project is
# installed without build isolation (an isolated build would pull a multi-GB CUDA torch); then the
# fused hash-grid kernel is compiled once into its on-disk cache. The client SDK (clients/python) is
# installed editable beside it; its dependencies (httpx, pydantic) are the project's already.
$(STAMP): pyproject.toml clients/python/pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip setuptools wheel
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet --no-build-isolation -e '.[test]'
	$(BIN)/pip install --quiet --no-deps --no-build-isolation -e clients/python
	$(BIN)/python -m model.nerf.encodings.kernels
	touch $(STAMP)

# Serve the committed demo bundle on 127.0.0.1:8000 (HYPNERF_PORT, HYPNERF_HOST and the other
# HYPNERF_* settings apply; see service/README.md). Loading checks every file's sha256 against the
# manifest and refuses a damaged bundle; `hypnerf export --verify BUNDLE` also checks ONNX parity.
run: install
	$(BIN)/hypnerf serve --bundle $(BUNDLE)

BUNDLE ?= bundles/chair-demo
SH3D := data/sh3d-chair-variants
PRIOR := runs/prior-cpu

# Rebuild the demo bundle from scratch on the project's own trainer: the Sweet Home 3D chairs with
# colour variants (about 5 min; needs `apt-get update` once for the furniture package), the prior
# (20000 steps, 64 min on 2 cores; resumes), the query network (embeds 48 renders per instance,
# cached, so a retrain takes minutes), the denoiser (TTO of 12 validation chairs for its pairs, then 3000 steps; about
# 20 min), then the export (about 2 min: it measures each instance's colours in renders). Steps already done
# are skipped. Remove runs/ and data/ to start over.
bundle: install
	test -f $(SH3D)/index.json || $(BIN)/hypnerf data import-sh3d --out $(SH3D) --category chair --variants 4 --views 91 --res 128
	test -f $(PRIOR)/hypernet.safetensors || $(BIN)/hypnerf train --data $(SH3D) --out $(PRIOR) --preset cpu --steps 20000 \
		--objects-per-step 8 --rays 4096 --validate-every 1000 --checkpoint-every 1000 $$(test -f $(PRIOR)/checkpoint.pt && echo --resume)
	test -f runs/query/cpu/query.safetensors || OMP_NUM_THREADS=1 $(BIN)/hypnerf train-query --run $(PRIOR) --data $(SH3D) --out runs/query/cpu --views 48 --head shape-codebook
	test -f runs/denoise/denoiser-tto/denoiser.safetensors || OMP_NUM_THREADS=1 $(BIN)/hypnerf train-denoiser --run $(PRIOR) --data $(SH3D) \
		--out runs/denoise/denoiser-tto --steps 3000 --instances 0 --tto-objects 12 --tto-views 24
	rm -rf $(BUNDLE)
	$(BIN)/hypnerf export --run $(PRIOR) --out $(BUNDLE) --data $(SH3D) --query runs/query/cpu --denoiser runs/denoise/denoiser-tto

demo: install
	$(BIN)/hypnerf demo --out runs/demo

test: install
	$(BIN)/python -m pytest -q

bench: install
	$(BIN)/pip install --quiet --no-deps nerfstudio==1.1.5 jaxtyping wadler_lindig rich viser msgspec websockets zstandard
	$(BIN)/python -m benchmarks.run_all

# The category prior (hours on 2 cores): dataset with colour variants, training, compression,
# ablation, disentanglement, then the hypernetwork presets compared. Stages already done are
# skipped; training resumes where it stopped.
bench-prior: install
	$(BIN)/python -m benchmarks.bench_prior
	$(BIN)/python -m benchmarks.bench_presets
	$(BIN)/python -m benchmarks.report

# What runs on the trained prior (about two hours on 2 cores; each stage is skipped when its result
# exists): inversion (generalisation table, views, speed, poses), the query network, the denoiser,
# and the service's latency on the demo bundle. One thread each: oversubscribed cores run torch
# many times slower.
bench-models: install
	OMP_NUM_THREADS=1 $(BIN)/python -m benchmarks.bench_inversion
	OMP_NUM_THREADS=1 $(BIN)/python -m benchmarks.bench_query
	OMP_NUM_THREADS=1 $(BIN)/python -m benchmarks.bench_denoise
	$(BIN)/python -m benchmarks.bench_service --bundle $(BUNDLE)
	$(BIN)/python -m benchmarks.report

data: install
	$(BIN)/hypnerf data synth --out data/synth --objects 16 --views 91 --res 128 --seed 0
	$(BIN)/hypnerf data import-sh3d --out data/sh3d-chair --category chair --views 91 --res 128

clean:
	rm -rf $(VENV) runs build *.egg-info
