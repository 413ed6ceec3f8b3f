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
# pipelines/Snakefile reads stage_code through make --eval, and each chain target's path: renaming them breaks it
# (tests/test_snakemake.py).
stage_code = stages/__init__.py $(wildcard stages/$(1).py) \
	$(if $(wildcard stages/$(1)/.),$(sort $(shell find stages/$(1) -name '*.py' -not -path '*/__pycache__/*'))) \
	$(CORE_CODE)

# The plan: the first stage recipe that runs in a make invocation prints the stages that will run, the time budget
# or estimate of each and the total (pipelines/plan.py, also kept in OUT/plan.txt). A make with nothing to do prints
# nothing and `make -n` only lists the line. PLAN_TOKEN tells one make invocation from the next; PLAN_MAKE hides
# $(MAKE) from the recipe text, or `make -n` would run the line.
PLAN := $(VENV)/bin/python pipelines/plan.py
PLAN_TOKEN := $(shell echo "$$PPID-$$RANDOM")
PLAN_MAKE := $(MAKE)
PLAN_GOALS := $(if $(filter undefined,$(origin MAKECMDGOALS)),all,$(or $(MAKECMDGOALS),all))
shquote = '$(subst ','"'"',$(1))'
show_plan = -@$(PLAN) show $(1) --token $(PLAN_TOKEN) --out=$(call shquote,$(OUT)) --make=$(call shquote,$(PLAN_MAKE)) \
	--makefile=$(call shquote,$(firstword $(MAKEFILE_LIST))) --goals=$(call shquote,$(PLAN_GOALS)) \
	--photos=$(call shquote,$(PHOTOS)) --posed=$(call shquote,$(POSED)) --poses-args=$(call shquote,$(POSES_ARGS)) \
	--train-args=$(call shquote,$(TRAIN_ARGS)) --render-args=$(call shquote,$(RENDER_ARGS)) \
	--depth-args=$(call shquote,$(DEPTH_ARGS)) --mesh-args=$(call shquote,$(MESH_ARGS))

# A rebuild replaces the run (--overwrite: the old one waits in run.previous/ until the new one succeeds).
$(RUN_DIR)/manifest.json: $(SCENE_DIR)/transforms.json $(call stage_code,train) | $(INSTALLED)
	$(call show_plan,train)
	$(NERFPIPE) train $(SCENE_DIR) $(RUN_DIR) --overwrite $(TRAIN_ARGS)

# The default video costs about half what training did: --max-seconds is half the training run's time (its
# manifest's used.train_seconds, at least 60 s; pipelines/plan.py RENDER_SHARE); render shrinks, then thins, the
# frames to fit. RENDER_ARGS come after it,
# so RENDER_ARGS='--max-seconds 3600' (or --frames, --downscale) asks for more.
$(OUT)/video.mp4: $(RUN_DIR)/manifest.json $(call stage_code,render) | $(INSTALLED)
	$(call show_plan,render)
	$(NERFPIPE) render $(RUN_DIR) $@ --path auto --max-seconds $$($(PLAN) render-seconds $(RUN_DIR)) $(RENDER_ARGS)

# depth reads the run through what eval leaves: eval keeps the test views' depth in the run's render cache
# (model/view_cache.py) and depth takes them from there instead of rendering again (a new eval.json, which a new run
# makes, remakes the maps: seconds). One prerequisite read, as pipelines/Snakefile's READS says.
$(OUT)/depth/manifest.json: $(OUT)/eval.json $(call stage_code,depth) | $(INSTALLED)
	$(call show_plan,depth)
	$(NERFPIPE) depth $(RUN_DIR) $(OUT)/depth --overwrite $(DEPTH_ARGS)

$(OUT)/eval.json: $(RUN_DIR)/manifest.json $(call stage_code,eval) | $(INSTALLED)
	$(call show_plan,eval)
	$(NERFPIPE) eval $(RUN_DIR) $@ $(EVAL_ARGS)

$(OUT)/mesh.ply: $(RUN_DIR)/manifest.json $(call stage_code,mesh) | $(INSTALLED)
	$(call show_plan,mesh)
	$(NERFPIPE) mesh $(RUN_DIR) $@ $(MESH_ARGS)

COMMON_OUTPUTS := $(RUN_DIR)/manifest.json $(OUT)/video.mp4 $(OUT)/depth/manifest.json $(OUT)/eval.json \
	$(OUT)/mesh.ply

# The chain's last word: one line per failed self-check in the records under OUT (poses_report.json and every
# manifest / report; `check`, `checks`: data/checks.py), or "self-checks: all N ok". A suspect result is reported,
# not an error (exit 0). Run by the root Makefile's `all` recipe once PIPELINE_OUTPUTS are built: it is never a
# prerequisite of a file, and it runs on every `make all`, even when nothing was rebuilt.
SUSPECTS = $(VENV)/bin/python pipelines/suspects.py $(call shquote,$(OUT))
