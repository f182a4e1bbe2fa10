# Mitsuba 3 reference renderer (optional; Python, never part of the Rust pipeline).
# Include from the top Makefile:   include tools/mitsuba/mitsuba.mk
# Targets (run from the repository root):
#   make mitsuba-ref SCENE=data/scenes/x.json OUT=out/x.mitsuba.exr [SPP=256] [VARIANT=scalar_rgb|llvm_ad_rgb]
#                    [MAX_BOUNCES=M] [SEED=S] [THREADS=T] [TIME=1] [MESH_OBJ="name=file.obj ..."]
#                    an OUT not ending in .exr is a folder: OUT/<scene name>.mitsuba.exr
#   make mitsuba-compare A=a.exr B=reference.exr [TOL_MEAN=0.02]
#   make mitsuba-speed [SCENE=...] [SPP=64] [THREADS=2] [ROUNDS=6] [MESH_OBJ=...]
#                    nppp and Mitsuba (VARIANT, default llvm_ad_rgb, rr_depth 5 and 3) run
#                    alternately; render time alone, medians and ratios
#   make mitsuba-conformance [VARIANT=...]     camera convention check against shared/conformance
#   make mitsuba-media [MEDIA_SCENES=...] [SPP=1024] translucent scenes: nppp (two seeds) against
#                    Mitsuba volpath; means within 1% and relMSE beside nppp's own noise
#   make mitsuba-venv                          just create .venv-mitsuba
#   make mitsuba-llvm                          install Debian's libllvm19 (for VARIANT=llvm_ad_rgb)
# SPP, MAX_BOUNCES and SEED default to the scene's render values (unless the including
# Makefile sets them, e.g. SPP ?= 64); THREADS to all cores.

# keep whatever default goal the including Makefile has
MITSUBA_SAVED_GOAL := $(.DEFAULT_GOAL)

MITSUBA_DIR     := $(patsubst %/,%,$(dir $(lastword $(MAKEFILE_LIST))))
MITSUBA_VENV    ?= .venv-mitsuba
MITSUBA_PYTHON  ?= python3
MITSUBA_PY      := $(MITSUBA_VENV)/bin/python
MITSUBA_STAMP   := $(MITSUBA_VENV)/.installed
MITSUBA_VARIANT  = $(or $(VARIANT),scalar_rgb)
MITSUBA_SUDO    := $(if $(filter 0,$(shell id -u)),,sudo)

# Dr.Jit's LLVM backend needs libLLVM >= 16: use DRJIT_LIBLLVM_PATH if set, else find Debian's.
MITSUBA_LLVM_PATH_ENV = DRJIT_LIBLLVM_PATH="$${DRJIT_LIBLLVM_PATH:-$$(ls /usr/lib/*/libLLVM-19.so /usr/lib/*/libLLVM.so.19* 2>/dev/null | head -n1)}"
MITSUBA_LLVM_ENV = $(if $(filter llvm%,$(MITSUBA_VARIANT)),$(MITSUBA_LLVM_PATH_ENV))

.PHONY: mitsuba-venv mitsuba-llvm mitsuba-ref mitsuba-compare mitsuba-conformance mitsuba-speed mitsuba-media

mitsuba-venv: $(MITSUBA_STAMP)

$(MITSUBA_STAMP): $(MITSUBA_DIR)/requirements.txt
	test -x $(MITSUBA_PY) || $(MITSUBA_PYTHON) -m venv $(MITSUBA_VENV)
	$(MITSUBA_PY) -m pip install --quiet --upgrade pip
	$(MITSUBA_PY) -m pip install --quiet -r $(MITSUBA_DIR)/requirements.txt
	touch $@

mitsuba-llvm:
	@if [ -n "$$DRJIT_LIBLLVM_PATH" ] || ls /usr/lib/*/libLLVM-19.so /usr/lib/*/libLLVM.so.19* >/dev/null 2>&1; then \
	  echo "libLLVM for Dr.Jit: present"; \
	else \
	  echo "installing Debian's libllvm19 for Mitsuba's llvm_ad_rgb variant"; \
	  $(MITSUBA_SUDO) apt-get update -q && $(MITSUBA_SUDO) apt-get install -y -q libllvm19; \
	fi

mitsuba-ref: $(MITSUBA_STAMP) $(if $(filter llvm%,$(MITSUBA_VARIANT)),mitsuba-llvm)
	@test -n "$(SCENE)" || { echo "usage: make mitsuba-ref SCENE=scene.json OUT=out.exr [SPP=N] [VARIANT=scalar_rgb|llvm_ad_rgb] [MAX_BOUNCES=M] [SEED=S] [THREADS=T] [TIME=1]"; exit 2; }
	@test -n "$(OUT)" || { echo "mitsuba-ref: OUT=file.exr is required"; exit 2; }
	$(MITSUBA_LLVM_ENV) $(MITSUBA_PY) $(MITSUBA_DIR)/render_mitsuba.py "$(SCENE)" --out "$(OUT)" \
	  --variant $(MITSUBA_VARIANT) $(if $(SPP),--spp $(SPP)) $(if $(MAX_BOUNCES),--max-bounces $(MAX_BOUNCES)) \
	  $(if $(SEED),--seed $(SEED)) $(if $(THREADS),--threads $(THREADS)) $(if $(filter-out 0,$(TIME)),--time) \
	  $(foreach m,$(MESH_OBJ),--mesh-obj "$(m)")

MEDIA_SCENES ?= $(wildcard data/scenes/translucent/*.json)
mitsuba-media: $(MITSUBA_STAMP) build
	$(MITSUBA_PY) $(MITSUBA_DIR)/check_media.py $(NPPP) $(MEDIA_SCENES) --spp $(or $(MEDIA_SPP),1024) \
	  --variant $(MITSUBA_VARIANT) $(foreach m,$(MESH_OBJ),--mesh-obj "$(m)")

mitsuba-compare: $(MITSUBA_STAMP)
	@test -n "$(A)" -a -n "$(B)" || { echo "usage: make mitsuba-compare A=test.exr B=reference.exr [TOL_MEAN=0.02]"; exit 2; }
	$(MITSUBA_PY) $(MITSUBA_DIR)/compare_exr.py "$(A)" "$(B)" $(if $(TOL_MEAN),--tol-mean $(TOL_MEAN))

MITSUBA_SPEED_VARIANT = $(or $(VARIANT),llvm_ad_rgb)
mitsuba-speed: $(MITSUBA_STAMP) mitsuba-llvm build
	@test -n "$(SCENE)" || { echo "usage: make mitsuba-speed SCENE=scene.json [SPP=64] [THREADS=2] [ROUNDS=6] [MESH_OBJ=NAME=FILE.obj]"; exit 2; }
	$(MITSUBA_LLVM_PATH_ENV) $(MITSUBA_PY) $(MITSUBA_DIR)/speed_compare.py "$(NPPP)" "$(SCENE)" \
	  --variant $(MITSUBA_SPEED_VARIANT) --spp $(or $(SPP),64) --threads $(or $(THREADS),2) --rounds $(or $(ROUNDS),6) \
	  $(foreach m,$(MESH_OBJ),--mesh-obj "$(m)")

mitsuba-conformance: $(MITSUBA_STAMP) $(if $(filter llvm%,$(MITSUBA_VARIANT)),mitsuba-llvm)
	$(MITSUBA_LLVM_ENV) $(MITSUBA_PY) $(MITSUBA_DIR)/check_conformance.py --variant $(MITSUBA_VARIANT)

.DEFAULT_GOAL := $(MITSUBA_SAVED_GOAL)
