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

.PHONY: all build render test bench clean help
all: render

help:
	@echo "make render   build, then render $(SCENE) to $(OUT)/ (EXR + PNG)"
	@echo "make test     run the test suite"
	@echo "make bench    criterion micro-benchmarks"

build:
	cargo build --release -p nppp-cli

# Phony on purpose: cargo decides what is stale.
$(NPPP): build

render: build
	$(NPPP) render $(SCENE) --spp $(SPP) --out $(OUT)/pt.exr --png $(OUT)/pt.png

test:
	cargo test --workspace

bench:
	cargo bench -p nppp-benches

clean:
	rm -rf $(OUT)

-include tools/mitsuba/mitsuba.mk
