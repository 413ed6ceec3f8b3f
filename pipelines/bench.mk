# Benchmarks (not tests): they read ../shared/data and print figures. Speed goals live here.
BENCH_OUT ?= runs/bench
.PHONY: bench bench-poses bench-train bench-ndc bench-mesh bench-turntable bench-refine bench-view
bench: bench-poses bench-train bench-ndc bench-mesh bench-turntable bench-refine bench-view

# issue 27: every real capture in ../shared/data through make PHOTOS= / POSED= (fox, lego_400, tiny npz, fern);
# one table, docs/BENCH_REAL.md, with the commit it was measured at (~1 h on 2 cores). A default changes only with it.
.PHONY: bench-real
bench-real: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_real --out $(BENCH_OUT)/real

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

# issue 48: the sdf method against the density method, same photos, same seconds (docs/SDF.md)
.PHONY: bench-sdf
bench-sdf: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_sdf --out $(BENCH_OUT)/sdf

.PHONY: bench-sdf-scenes
bench-sdf-scenes: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_sdf --out $(BENCH_OUT)/sdf_scenes --scenes

# issue 29: the default textured mesh of a real capture against its field, on its held-out cameras (the fox run
# that bench-real makes; MESH_RUN=DIR for another)
MESH_RUN ?= $(BENCH_OUT)/real/fox/run
.PHONY: bench-mesh-texture
bench-mesh-texture: $(INSTALLED)
	@test -f $(MESH_RUN)/checkpoint.pt || { echo "bench-mesh-texture: no trained run at $(MESH_RUN) (make bench-real makes it, or MESH_RUN=DIR)"; exit 2; }
	$(VENV)/bin/python -m benchmarks.bench_mesh_texture $(MESH_RUN) --out $(BENCH_OUT)/mesh_texture

# issue 30: splats (`nerfpipe splat`, 300 s) from bench-real's fox and lego_400 runs against their fields, on the
# same held-out views (PSNR, SSIM, seconds a frame); ~20 min. make bench-real first.
.PHONY: bench-splat
bench-splat: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_splat --runs $(BENCH_OUT)/real --out $(BENCH_OUT)/splat

# Peak RSS of train against view count at 1920x1080 (issue 19: big captures in bounded memory); ~5 min.
.PHONY: bench-memory
bench-memory: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_memory --views 100,300 --downscale 1 --out $(BENCH_OUT)/memory
	$(VENV)/bin/python -m benchmarks.bench_memory --views 100,300,1000 --downscale auto --out $(BENCH_OUT)/memory

# a synthetic turntable (object turns, camera and room fixed): poses with masks vs without, then 120 s of training
bench-turntable: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_turntable --out $(BENCH_OUT)/turntable

# issue 17: train --refine-poses on 3 deg / 3 % perturbed cameras, --appearance on per-view gains and casts (120 s runs)
bench-refine: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_refine --out $(BENCH_OUT)/refine

# issue 16: the viewer's 256 px preview (coarse / refined) against render's path, on lego_400's run from bench-train
VIEW_RUN ?= $(BENCH_OUT)/train/lego_400/density
bench-view: $(INSTALLED)
	@test -f $(VIEW_RUN)/checkpoint.pt || { echo "bench-view: no trained run at $(VIEW_RUN) (make bench-train makes it, or VIEW_RUN=DIR)"; exit 2; }
	$(VENV)/bin/python -m benchmarks.bench_view $(VIEW_RUN)

# issue 53: printed boxes whose faces look alike (carton, cube), photographed all round on white, through poses
# against their exact poses: right within 1 deg, or flagged with the right cause (~30 min on 2 cores);
# docs/BENCH_FOLDING.md
.PHONY: bench-folding
bench-folding: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_folding --out $(BENCH_OUT)/folding

# issue 53: the shared head through poses (masked, on white, as shot, 22 photos at 4000 px) against its own poses
.PHONY: bench-head
bench-head: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_head --out $(BENCH_OUT)/head

# issue 51: every GPU figure in one script, one table (benchmarks/bench_gpu.py); on the device machine, which has no
# venv of ours: `make bench-gpu-pack` here (copies lego_800 and the fox into the git-ignored .gpu-data/), then carry
# .gpu-data and run `python -m benchmarks.bench_gpu --data .gpu-data` there. Without CUDA it stops in one line.
.PHONY: bench-gpu bench-gpu-pack bench-gpu-smoke
bench-gpu: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_gpu --out $(BENCH_OUT)/gpu

bench-gpu-pack: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_gpu --pack .gpu-data

# every row at toy sizes on any device (what tests/test_bench_gpu.py runs)
bench-gpu-smoke: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_gpu --smoke --out $(BENCH_OUT)/gpu-smoke
