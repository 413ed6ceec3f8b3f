# X-ray / CT: a CT volume -> simulated projections -> attenuation field -> metrics, slices, DRR/MIP video, mesh.
#   make XRAY=volume.mat OUT=runs/ct        (.npy, .mat, .raw with XRAY_SIM_ARGS='--shape X,Y,Z --dtype ...', .nii)
# Outputs: OUT/projections/ (the projection scene), OUT/xray_run/ (the trained run, volume.npy), OUT/xray_eval.json
# (3-D PSNR/SSIM, projection PSNR/SSIM, FDK beside it), OUT/xray/ (slices*.png, drr_mip.mp4, mesh.ply).
# Options per stage: XRAY_SIM_ARGS, XRAY_TRAIN_ARGS, XRAY_EVAL_ARGS, XRAY_EXPORT_ARGS.
# `make bench-xray`: benchmarks/bench_xray.py (TIGRE thorax 128^3, 50/25/10 cone-beam views, field vs FDK).
XRAY ?=
XRAY_SIM_ARGS ?=
XRAY_TRAIN_ARGS ?=
XRAY_EVAL_ARGS ?=
XRAY_EXPORT_ARGS ?=
XRAY_SCENE := $(OUT)/projections
XRAY_RUN := $(OUT)/xray_run
XRAY_OUTPUTS :=

ifneq ($(XRAY),)
$(XRAY_SCENE)/manifest.json: $(XRAY) $(call stage_code,xray_simulate) | $(INSTALLED)
	$(NERFPIPE) xray-simulate $(XRAY) $(XRAY_SCENE) --overwrite $(XRAY_SIM_ARGS)

$(XRAY_RUN)/manifest.json: $(XRAY_SCENE)/manifest.json $(call stage_code,xray_train) | $(INSTALLED)
	$(NERFPIPE) xray-train $(XRAY_SCENE) $(XRAY_RUN) --overwrite $(XRAY_TRAIN_ARGS)

$(OUT)/xray_eval.json: $(XRAY_RUN)/manifest.json $(call stage_code,xray_eval) | $(INSTALLED)
	$(NERFPIPE) xray-eval $(XRAY_RUN) $@ $(XRAY_EVAL_ARGS)

$(OUT)/xray/manifest.json: $(XRAY_RUN)/manifest.json $(call stage_code,xray_export) | $(INSTALLED)
	$(NERFPIPE) xray-export $(XRAY_RUN) $(OUT)/xray --overwrite $(XRAY_EXPORT_ARGS)

XRAY_OUTPUTS := $(XRAY_SCENE)/manifest.json $(XRAY_RUN)/manifest.json $(OUT)/xray_eval.json $(OUT)/xray/manifest.json
endif

.PHONY: bench-xray
bench-xray: $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.bench_xray --out $(BENCH_OUT)/xray
