# Photos or a video: poses (COLMAP) -> convert -> the common chain.
POSES_ARGS ?=
ifneq ($(PHOTOS),)
# every photo is a prerequisite: adding or changing one re-runs COLMAP
PHOTO_FILES := $(if $(wildcard $(PHOTOS)/.),$(wildcard $(PHOTOS)/*),$(PHOTOS))

# colmap/manifest.json exists only after a success (poses_report.json is also written on failure, and
# .DELETE_ON_ERROR would delete that report, which says what went wrong).
$(SCENE_DIR)/colmap/manifest.json: $(PHOTO_FILES) $(call stage_code,poses) | $(INSTALLED)
	$(call show_plan,poses)
	$(NERFPIPE) poses $(PHOTOS) $(SCENE_DIR) $(POSES_ARGS)

$(SCENE_DIR)/transforms.json: $(SCENE_DIR)/colmap/manifest.json $(call stage_code,convert) | $(INSTALLED)
	$(call show_plan,convert)
	$(NERFPIPE) convert $(SCENE_DIR)/colmap/sparse $(SCENE_DIR)

PIPELINE_OUTPUTS := $(SCENE_DIR)/colmap/manifest.json $(SCENE_DIR)/transforms.json $(COMMON_OUTPUTS)
endif
