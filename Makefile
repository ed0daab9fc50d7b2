# The two commands of README.md: `make demo` (the main job on the embedded default) and `make test`
# (format, lints, every test). Both run the idempotent set-up first.
SHELL := /bin/bash
CARGO ?= cargo

# ccache for the C/C++ parts (faiss, later) so a second cold build takes seconds.
export CMAKE_C_COMPILER_LAUNCHER ?= ccache
export CMAKE_CXX_COMPILER_LAUNCHER ?= ccache
export ORT_DYLIB_PATH ?= $(CURDIR)/.deps/onnxruntime/libonnxruntime.so.1.31.1
export OPENVINO_DYLIB_PATH ?= $(CURDIR)/.deps/openvino/libopenvino_c.so.2641
export PNTR_PYTHON ?= $(CURDIR)/.deps/venv/bin/python

.PHONY: setup demo test fmt lint unit bench

setup:
	@bash scripts/setup.sh

demo: setup
	$(CARGO) run --release -p pntr-cli --bin pntr -- demo

fmt: setup
	$(CARGO) fmt --all -- --check

lint: setup
	$(CARGO) clippy --workspace --all-targets -- -D warnings
	$(CARGO) clippy -p pntr-features -p pntr-service --features cuda -- -D warnings

unit: setup
	@if $(CARGO) nextest --version >/dev/null 2>&1; then \
	  $(CARGO) nextest run --workspace --no-fail-fast; \
	else \
	  $(CARGO) test --workspace --no-fail-fast; \
	fi

test: fmt lint unit

bench: setup
	$(CARGO) bench -p pntr-synth --bench render
	$(CARGO) bench -p pntr-registration --bench registration
	$(CARGO) bench -p pntr-pipeline --bench verify
	$(CARGO) run --release -p pntr-retrieval --example retrieval_scaling
