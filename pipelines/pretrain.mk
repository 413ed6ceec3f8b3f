# issue 49: the gnt model nerfpipe ships (model/methods/gnt/weights/pretrained.pt), made from generated scenes only.
#   make pretrain-gnt                      # the recipe below: scenes, then PRETRAIN_SECONDS of training
#   make pretrain-gnt PRETRAIN_DEVICE=cuda PRETRAIN_SECONDS=3600
#   make pretrain-gnt PRETRAIN_INIT=pretrained   # continue the shipped weights (pretrained.json keeps what made them)
# The scenes: --subject random (a seed draws the objects, their textures and the lights) in three layouts, objects
# with alpha seen all round, forward-facing captures before a wall, orbits inside a room; seeds 100000 and up
# (bench-gnt holds out seeds 900000 and up). The weights and pretrained.json (command, commit, recipe, figures) are
# written into the package; commit them.
PRETRAIN_OUT ?= runs/pretrain_gnt
PRETRAIN_SECONDS ?= 2400
PRETRAIN_DEVICE ?= auto
PRETRAIN_THREADS ?= 1
PRETRAIN_SCENES ?= 60
PRETRAIN_SIZE ?= 80
PRETRAIN_VIEWS ?= 16
PRETRAIN_INIT ?=
GNT_WEIGHTS := model/methods/gnt/weights

.PHONY: pretrain-gnt pretrain-gnt-scenes
pretrain-gnt-scenes: $(INSTALLED)
	$(VENV)/bin/nerfpipe scene $(PRETRAIN_OUT)/scenes/orbit --subject random --kind rgba --layout orbit \
		--count $(PRETRAIN_SCENES) --seed 100000 --size $(PRETRAIN_SIZE) --views $(PRETRAIN_VIEWS) --overwrite
	$(VENV)/bin/nerfpipe scene $(PRETRAIN_OUT)/scenes/forward --subject random --kind posed --layout forward \
		--count $(PRETRAIN_SCENES) --seed 200000 --size $(PRETRAIN_SIZE) --views $(PRETRAIN_VIEWS) --overwrite
	$(VENV)/bin/nerfpipe scene $(PRETRAIN_OUT)/scenes/room --subject random --kind posed --layout room \
		--count $(PRETRAIN_SCENES) --seed 300000 --size $(PRETRAIN_SIZE) --views $(PRETRAIN_VIEWS) --overwrite

pretrain-gnt: pretrain-gnt-scenes
	$(VENV)/bin/nerfpipe pretrain-gnt $(PRETRAIN_OUT)/scenes $(PRETRAIN_OUT)/model --max-seconds $(PRETRAIN_SECONDS) \
		--device $(PRETRAIN_DEVICE) --threads $(PRETRAIN_THREADS) $(if $(PRETRAIN_INIT),--init $(PRETRAIN_INIT)) --overwrite
	$(VENV)/bin/python -m benchmarks.ship_weights $(PRETRAIN_OUT)/model $(GNT_WEIGHTS) \
		--command "make pretrain-gnt PRETRAIN_SECONDS=$(PRETRAIN_SECONDS) PRETRAIN_SCENES=$(PRETRAIN_SCENES) PRETRAIN_SIZE=$(PRETRAIN_SIZE) PRETRAIN_VIEWS=$(PRETRAIN_VIEWS) PRETRAIN_DEVICE=$(PRETRAIN_DEVICE)$(if $(PRETRAIN_INIT), PRETRAIN_INIT=$(PRETRAIN_INIT))"

# issue 49: GNT zero-shot on held-out generated scenes (3, 6, 10 photos) against the density method on the same
# photos, zero-shot on lego_400 and the fern, per-scene against density (docs/GNT.md has the table and the commit).
.PHONY: bench-gnt
bench-gnt: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_gnt --out $(BENCH_OUT)/gnt

# issue 50: the single-view voxel network. The data: `nerfpipe shapes` (VOXEL_COUNT objects of each trained family,
# seeds 0 and up, VOXEL_VIEWS photos each; bench-voxels holds out seeds 100000 and up and the family `sofa`), then
# VOXEL_SECONDS of training (VOXEL_INIT=weights.pt continues earlier weights: their provenance is kept inside); the
# weights and pretrained.json (command, commit, data, figures) go into the package.
VOXEL_OUT ?= runs/pretrain_voxels
VOXEL_COUNT ?= 400
VOXEL_VIEWS ?= 6
VOXEL_SECONDS ?= 2400
VOXEL_DEVICE ?= auto
VOXEL_INIT ?=
VOXEL_LR ?= 1e-3
VOXEL_WEIGHTS := model/voxels/weights

.PHONY: pretrain-voxels bench-voxels
$(VOXEL_OUT)/shapes/manifest.json: $(INSTALLED)
	$(VENV)/bin/nerfpipe shapes $(VOXEL_OUT)/shapes --count $(VOXEL_COUNT) --views $(VOXEL_VIEWS) --overwrite

pretrain-voxels: $(VOXEL_OUT)/shapes/manifest.json
	$(VENV)/bin/nerfpipe pretrain-voxels $(VOXEL_OUT)/shapes $(VOXEL_OUT)/model --max-seconds $(VOXEL_SECONDS) \
		--device $(VOXEL_DEVICE) --lr $(VOXEL_LR) $(if $(VOXEL_INIT),--init $(VOXEL_INIT)) --overwrite
	$(VENV)/bin/python -m benchmarks.ship_weights $(VOXEL_OUT)/model $(VOXEL_WEIGHTS) \
		--command "make pretrain-voxels VOXEL_COUNT=$(VOXEL_COUNT) VOXEL_VIEWS=$(VOXEL_VIEWS) VOXEL_SECONDS=$(VOXEL_SECONDS) VOXEL_DEVICE=$(VOXEL_DEVICE) VOXEL_LR=$(VOXEL_LR)$(if $(VOXEL_INIT), VOXEL_INIT=$(VOXEL_INIT))"

# issue 50: IoU on held-out objects and the held-out family (1 and 5 photos), the scanned meshes, a real photo
# (docs/VOXELS.md has the table and the commit).
bench-voxels: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_voxels --out $(BENCH_OUT)/voxels
