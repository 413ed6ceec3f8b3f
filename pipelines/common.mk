# The stages every scene shares once it has a transforms.json: train -> render, depth, eval, mesh.
# Variables: OUT (the run's folder). SCENE_DIR/transforms.json comes from photos.mk or posed.mk.
SCENE_DIR := $(OUT)/scene
RUN_DIR := $(OUT)/run

TRAIN_ARGS ?=
RENDER_ARGS ?=
DEPTH_ARGS ?=
EVAL_ARGS ?=
MESH_ARGS ?=

# The code a stage runs, and nothing else (no benchmarks, no tests): cli.py, the core packages radiance/,
# data/ and model/ (every .py below them, found afresh on each make run), stages/__init__.py, and the stage's
# own module stages/NAME.py or package stages/NAME/ (stages never import one another: tests/test_layering.py).
CORE_CODE := cli.py $(sort $(shell find $(wildcard radiance data model) -name '*.py' -not -path '*/__pycache__/*'))
stage_code = stages/__init__.py $(wildcard stages/$(1).py) \
	$(if $(wildcard stages/$(1)/.),$(sort $(shell find stages/$(1) -name '*.py' -not -path '*/__pycache__/*'))) \
	$(CORE_CODE)

$(RUN_DIR)/manifest.json: $(SCENE_DIR)/transforms.json $(call stage_code,train) | $(INSTALLED)
	$(NERFPIPE) train $(SCENE_DIR) $(RUN_DIR) $(TRAIN_ARGS)

$(OUT)/video.mp4: $(RUN_DIR)/manifest.json $(call stage_code,render) | $(INSTALLED)
	$(NERFPIPE) render $(RUN_DIR) $@ --path auto $(RENDER_ARGS)

$(OUT)/depth/manifest.json: $(RUN_DIR)/manifest.json $(call stage_code,depth) | $(INSTALLED)
	$(NERFPIPE) depth $(RUN_DIR) $(OUT)/depth $(DEPTH_ARGS)

$(OUT)/eval.json: $(RUN_DIR)/manifest.json $(call stage_code,eval) | $(INSTALLED)
	$(NERFPIPE) eval $(RUN_DIR) $@ $(EVAL_ARGS)

$(OUT)/mesh.ply: $(RUN_DIR)/manifest.json $(call stage_code,mesh) | $(INSTALLED)
	$(NERFPIPE) mesh $(RUN_DIR) $@ $(MESH_ARGS)

COMMON_OUTPUTS := $(RUN_DIR)/manifest.json $(OUT)/video.mp4 $(OUT)/depth/manifest.json $(OUT)/eval.json \
	$(OUT)/mesh.ply
