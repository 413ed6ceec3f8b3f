# `make study` (~12 min on 2 CPU cores) and `make study-quick` (~1.5 min): one Markdown page with plots and tables,
# STUDY_OUT/README.md (written last: the sentinel), from benchmarks/study.py: compositing error against samples and
# time, the stiff sweep (radiance/stability.py, shared with tests/test_compositing.py), training PSNR against seconds,
# mesh Chamfer against resolution, fit-image. It reruns when the code it runs changes; `make -B study` forces it.
# Variables: STUDY_OUT, STUDY_QUICK_OUT, STUDY_ARGS (e.g. --threads 2, --sections compositing,stability).
STUDY_OUT ?= runs/study
STUDY_QUICK_OUT ?= runs/study-quick
STUDY_ARGS ?=
STUDY_CODE := benchmarks/__init__.py benchmarks/study.py benchmarks/bench_mesh.py benchmarks/mesh_metrics.py \
	benchmarks/standin.py $(sort $(foreach s,scene convert train report mesh fit_image,$(call stage_code,$(s))))

.PHONY: study study-quick
study: $(STUDY_OUT)/README.md
study-quick: $(STUDY_QUICK_OUT)/README.md

$(STUDY_OUT)/README.md: $(STUDY_CODE) | $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.study --out $(STUDY_OUT) $(STUDY_ARGS)

$(STUDY_QUICK_OUT)/README.md: $(STUDY_CODE) | $(INSTALLED)
	$(VENV)/bin/python -m benchmarks.study --quick --out $(STUDY_QUICK_OUT) $(STUDY_ARGS)
