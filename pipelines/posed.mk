# An already-posed dataset (COLMAP model, Blender, LLFF, tiny-NeRF npz, transforms.json): no `poses` stage.
# CONVERT_ARGS: convert's options, e.g. CONVERT_ARGS='--images images_8' for an LLFF capture's small copies.
CONVERT_ARGS ?=
ifneq ($(POSED),)
POSED_FILES := $(if $(wildcard $(POSED)/.),$(wildcard $(POSED)/*.json $(POSED)/*.npy $(POSED)/*.npz),$(POSED))

$(SCENE_DIR)/transforms.json: $(POSED_FILES) $(call stage_code,convert) | $(INSTALLED)
	$(call show_plan,convert)
	$(NERFPIPE) convert $(POSED) $(SCENE_DIR) $(CONVERT_ARGS)

PIPELINE_OUTPUTS := $(SCENE_DIR)/transforms.json $(COMMON_OUTPUTS)
endif
