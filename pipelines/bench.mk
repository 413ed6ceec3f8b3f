# Benchmarks (not tests): they read ../shared/data and print figures. Speed goals live here.
BENCH_OUT ?= runs/bench
.PHONY: bench bench-poses bench-train bench-ndc bench-mesh bench-refine
bench: bench-poses bench-train bench-ndc bench-mesh bench-refine

bench-poses: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_poses --out $(BENCH_OUT)/poses

# through the CLI on the files as distributed: tiny npz (120 s), the small-scale Blender scene (2 x 120 s), lego_400 (900 s)
bench-train: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_train --dataset tiny --out $(BENCH_OUT)/train
	$(VENV)/bin/python -m benchmarks.bench_train --dataset small --out $(BENCH_OUT)/train
	$(VENV)/bin/python -m benchmarks.bench_train --dataset lego_400 --seconds 900 --out $(BENCH_OUT)/train

bench-ndc: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_ndc --out $(BENCH_OUT)/ndc

bench-mesh: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_mesh --out $(BENCH_OUT)/mesh

# issue 17: train --refine-poses on 3 deg / 3 % perturbed cameras, --appearance on per-view gains and casts (120 s runs)
bench-refine: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_refine --out $(BENCH_OUT)/refine
