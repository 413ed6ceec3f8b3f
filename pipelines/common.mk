# The stages every scene shares once it has a transforms.json: train -> render, depth, eval, mesh.
# Variables: OUT (the run's folder). SCENE_DIR/transforms.json comes from photos.mk or posed.mk.
SCENE_DIR := $(OUT)/scene
RUN_DIR := $(OUT)/run

TRAIN_ARGS ?=
RENDER_ARGS ?=
DEPTH_ARGS ?=
EVAL_ARGS ?=
MESH_ARGS ?=

CORE_CODE := $(wildcard radiance/*.py radiance/fields/*.py data/*.py data/importers/*.py) cli.py

$(RUN_DIR)/manifest.json: $(SCENE_DIR)/transforms.json stages/train.py $(CORE_CODE) | $(INSTALLED)
	$(NERFPIPE) train $(SCENE_DIR) $(RUN_DIR) $(TRAIN_ARGS)

$(OUT)/video.mp4: $(RUN_DIR)/manifest.json stages/render.py $(CORE_CODE) | $(INSTALLED)
	$(NERFPIPE) render $(RUN_DIR) $@ --path auto $(RENDER_ARGS)

$(OUT)/depth/manifest.json: $(RUN_DIR)/manifest.json stages/depth.py $(CORE_CODE) | $(INSTALLED)
	$(NERFPIPE) depth $(RUN_DIR) $(OUT)/depth $(DEPTH_ARGS)

$(OUT)/eval.json: $(RUN_DIR)/manifest.json stages/eval.py $(CORE_CODE) | $(INSTALLED)
	$(NERFPIPE) eval $(RUN_DIR) $@ $(EVAL_ARGS)

$(OUT)/mesh.ply: $(RUN_DIR)/manifest.json $(wildcard stages/mesh*.py) $(CORE_CODE) | $(INSTALLED)
	$(NERFPIPE) mesh $(RUN_DIR) $@ $(MESH_ARGS)

COMMON_OUTPUTS := $(RUN_DIR)/manifest.json $(OUT)/video.mp4 $(OUT)/depth/manifest.json $(OUT)/eval.json \
	$(OUT)/mesh.ply
