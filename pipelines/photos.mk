# Photos or a video: poses (COLMAP) -> convert -> the common chain.
POSES_ARGS ?=
ifneq ($(PHOTOS),)
# every photo is a prerequisite: adding or changing one re-runs COLMAP
PHOTO_FILES := $(if $(wildcard $(PHOTOS)/.),$(wildcard $(PHOTOS)/*),$(PHOTOS))

$(SCENE_DIR)/poses_report.json: $(PHOTO_FILES) $(wildcard stages/poses*.py) $(CORE_CODE) | $(INSTALLED)
	$(NERFPIPE) poses $(PHOTOS) $(SCENE_DIR) $(POSES_ARGS)

$(SCENE_DIR)/transforms.json: $(SCENE_DIR)/poses_report.json stages/convert.py | $(INSTALLED)
	$(NERFPIPE) convert $(SCENE_DIR)/colmap/sparse $(SCENE_DIR)

PIPELINE_OUTPUTS := $(SCENE_DIR)/poses_report.json $(SCENE_DIR)/transforms.json $(COMMON_OUTPUTS)
endif
