# nppp pipeline. `make render` on a fresh clone builds the tool and renders the
# default scene; `make test` runs the test suite (what CI runs).
#
# The cargo target directory lives outside the clone so that rebuilding a fresh
# clone reuses compiled dependencies.

export CARGO_TARGET_DIR ?= $(HOME)/.cache/nppp-target
NPPP := $(CARGO_TARGET_DIR)/release/nppp
SCENE ?= data/scenes/cornell-box.json
SPP ?= 64
OUT ?= out

# An object's estimator: data -> model -> baked file. The baked files are
# committed, so a fresh clone renders with them at once; `make bake` re-bakes
# one (making the data and the model first if they are missing). OBJECT picks
# which: knot (the default scene's diffuse knot), glass (the same knot as
# smooth glass, data/scenes/cornell-glass.json) or gold (a rough gold
# conductor, data/scenes/cornell-gold.json) or jade (a dense translucent
# medium inside a smooth boundary, data/scenes/cornell-jade.json) or tube
# (the open U-bent tube of data/scenes/tube.json, models/tube.nppp), e.g.
# `make bake OBJECT=glass`.
OBJECT ?= knot
OBJECT_SCENE_knot := data/scenes/cornell-box.json
OBJECT_SCENE_glass := data/scenes/cornell-glass.json
OBJECT_SCENE_gold := data/scenes/cornell-gold.json
OBJECT_SCENE_jade := data/scenes/cornell-jade.json
OBJECT_SCENE_tube := data/scenes/tube.json
OBJECT_SCENE := $(or $(OBJECT_SCENE_$(OBJECT)),$(error OBJECT=$(OBJECT): choose knot, glass, gold, jade or tube))
OBJECT_INSTANCE_tube := 4
OBJECT_INSTANCE := $(or $(OBJECT_INSTANCE_$(OBJECT)),6)
OBJECT_NAME_tube := tube
OBJECT_NAME := $(or $(OBJECT_NAME_$(OBJECT)),cornell-$(OBJECT))
DATA := $(OUT)/data/$(OBJECT_NAME).nppd
MODEL := $(OUT)/model/$(OBJECT_NAME)
ESTIMATOR := models/$(OBJECT_NAME).nppp
# The committed estimator was made with exactly these (crates/nppp-nn/README.md):
# 1 M rays (about half a minute, 312 MiB with each exit's picked vertex),
# 24000 training steps (about 21 minutes on 2 cores with the vertex head and
# the knot's 32-wide decoders, 33 with 64-wide ones; --minutes 0 keeps the
# run bit-reproducible), latent grid 32^4 at 4 bits and mask grid 64^4 at 4
# bits (16 MiB in all).
# `nppp gen`'s and `nppp train`'s defaults are that recipe
# (nppp-estimator/src/recipe.rs): 1 M rays, k = 64.
# Jade's walks average 95 scattering events (the knot's: 2), so its data is
# 300 k rays (about 5 minutes on 2 cores) instead of 1 M.
GEN_RAYS_jade := --rays 300000
GEN_FLAGS ?= --seed 0 $(GEN_RAYS_$(OBJECT))
# The gold estimator was trained with the recipe shortened to 10000 steps
# (about 8 minutes on 2 cores with its vertex head), as was jade; the knot
# with the full 24000 (about 21 minutes) and glass with twice that, 48000
# (about 27 minutes). Glass at 10000 steps rendered cornell-glass 0.5% too
# bright with 1.07x the relMSE of 24000; 48000 has 0.93x the relMSE of 24000
# there, at its oracle's (BENCHMARKS.md, "cornell-glass").
TRAIN_STEPS_gold := --steps 10000
TRAIN_STEPS_jade := --steps 10000
TRAIN_STEPS_glass := --steps 48000
# The opaque knots' decoders and vertex heads are 32 wide (3,488
# multiply-adds a row instead of 11,072): the same relMSE or less, and
# entries cheap enough to lift NPPP by 8-16% at equal error; glass keeps 64,
# where 32 had 1.04x the relMSE at P = 1 (BENCHMARKS.md, "Smaller decoders").
TRAIN_MODEL_knot := --decoder-width 32
TRAIN_MODEL_gold := --decoder-width 32
TRAIN_MODEL_tube := --decoder-width 32
TRAIN_FLAGS ?= --seed 1 --minutes 0 $(TRAIN_STEPS_$(OBJECT)) $(TRAIN_MODEL_$(OBJECT))
BAKE_FLAGS ?= --latent-grid 32 --bits 4 --mask-grid 64 --mask-bits 4

.PHONY: all build render test test-wgpu test-cluster bench clean help data train bake speed
all: render

help:
	@echo "make render   build, then render $(SCENE) to $(OUT)/ (EXR + PNG)"
	@echo "make test     run the test suite"
	@echo "make test-cluster  shards on a one-node Slurm cluster (installs slurm-wlm, munge)"
	@echo "make bench    nppp bench --quick (time vs error) and criterion micro-benchmarks"

# The renderer is built for this machine's CPU (as Mitsuba's LLVM variant
# JIT-compiles for it): 12% more samples/s on the default scene, measured.
# The binary then runs only on CPUs with the same instruction sets, and its
# images differ from a portable build's in the last bits (each build is
# deterministic). NATIVE=0 builds a portable binary.
NATIVE ?= 1
RELEASE_RUSTFLAGS := $(if $(filter 1,$(NATIVE)),-C target-cpu=native)

build:
	RUSTFLAGS="$(RELEASE_RUSTFLAGS)" cargo build --release -p nppp-cli

# Phony on purpose: cargo decides what is stale.
$(NPPP): build

data: $(DATA)
$(DATA): $(OBJECT_SCENE) | build
	$(NPPP) gen --scene $(OBJECT_SCENE) --instance $(OBJECT_INSTANCE) $(GEN_FLAGS) --overwrite --out $@

train: $(MODEL)/checkpoint/model.bpk
$(MODEL)/checkpoint/model.bpk: $(DATA) | build
	$(NPPP) train --data $(DATA) --out $(MODEL) $(TRAIN_FLAGS)

# Always re-bakes (a couple of minutes); data and model are made first only
# if missing. Not a prerequisite of `render`: the baked file is committed, and
# a render must never start a training run.
bake: $(MODEL)/checkpoint/model.bpk | build
	$(NPPP) bake --model $(MODEL) $(BAKE_FLAGS) --out $(ESTIMATOR)

# A high-spp plain path-traced reference, rendered once and kept.
REF_SPP ?= 1024
REFERENCE := $(OUT)/reference-$(notdir $(basename $(SCENE)))-$(REF_SPP).exr
$(REFERENCE): | build
	$(NPPP) render $(SCENE) --spp $(REF_SPP) --seed 1000 --estimators off --out $@

# Renders the default scene twice, plain path tracing and with
# `--estimators auto` (a pilot decides whether the committed estimator pays,
# and from which P; never retrained or re-baked by this target), and prints
# the decision and the time and error of each against the reference.
render: build $(REFERENCE)
	$(NPPP) render $(SCENE) --spp $(SPP) --estimators off --reference $(REFERENCE) --out $(OUT)/pt.exr --png $(OUT)/pt.png
	$(NPPP) render $(SCENE) --spp $(SPP) --estimators auto --reference $(REFERENCE) --out $(OUT)/nppp.exr --png $(OUT)/nppp.png

test:
	cargo test --workspace
	$(MAKE) test-wgpu

# The wgpu backend (training and the batched decoder) on whatever Vulkan
# driver is installed; on a machine without a GPU that is Mesa's lavapipe
# (`apt install mesa-vulkan-drivers`, which .ci/run does). Skipped with a
# note when no Vulkan driver is installed at all.
VULKAN_ICDS := $(wildcard /usr/share/vulkan/icd.d/*.json /etc/vulkan/icd.d/*.json)
test-wgpu:
ifneq ($(strip $(VULKAN_ICDS))$(VK_ICD_FILENAMES)$(VK_DRIVER_FILES),)
	XDG_RUNTIME_DIR=$${XDG_RUNTIME_DIR:-/tmp} cargo test --profile wgpu-smoke -p nppp-nn --features wgpu --test wgpu
else
	@echo "test-wgpu: skipped, no Vulkan driver installed (apt install mesa-vulkan-drivers)"
endif

# Shards on a real Slurm (not part of `make test`; needs root or sudo):
# installs slurm-wlm and munge, starts a one-node cluster on loopback, runs
# tools/slurm/submit.sh for a render and a data set, checks the merged files
# against single-machine runs byte for byte, shuts the cluster down.
test-cluster: build
	NPPP=$(NPPP) tools/slurm/test-cluster.sh

# Run time against error on the benchmark scenes (see BENCHMARKS.md), then
# the criterion micro-benchmarks.
bench: build
	$(NPPP) bench --quick
	RUSTFLAGS="$(RELEASE_RUSTFLAGS)" cargo bench -p nppp-benches

# Side by side with Mitsuba 3 on the default scene (optional, Python): the
# procedural knot is exported to OBJ for Mitsuba first. README "Speed".
speed: build
	mkdir -p $(OUT)
	$(NPPP) mesh --scene $(OBJECT_SCENE) --mesh knot --out $(OUT)/knot.obj --overwrite
	$(MAKE) mitsuba-speed SCENE=$(OBJECT_SCENE) THREADS=$(or $(THREADS),2) MESH_OBJ=knot=$(OUT)/knot.obj

clean:
	rm -rf $(OUT)

-include tools/mitsuba/mitsuba.mk
