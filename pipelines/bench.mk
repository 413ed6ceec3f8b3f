# Benchmarks (not tests): they read ../shared/data and print figures. Speed goals live here.
BENCH_OUT ?= runs/bench
.PHONY: bench bench-poses bench-train bench-ndc bench-mesh
bench: bench-poses bench-train bench-ndc bench-mesh

bench-poses: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_poses --out $(BENCH_OUT)/poses

bench-train: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_train --out $(BENCH_OUT)/train

bench-ndc: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_ndc --out $(BENCH_OUT)/ndc

bench-mesh: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_mesh --out $(BENCH_OUT)/mesh
