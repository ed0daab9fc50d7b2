#!/usr/bin/env bash
# Mutation fuzzing with a time budget: `scripts/fuzz.sh [SECONDS_PER_TARGET]` (default 60).
# Runs the targets of tests/fuzz_inputs.rs (request, mapfile, hdf5) and the CSV target of
# client/tests/register.rs with a time-derived seed and prints the executions per target.
# An input that fails is written to $TMPDIR/pntr-fuzz-<target>/; after fixing the bug, copy it into
# tests/fuzz/<target>/ so CI replays it on every run.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export ORT_DYLIB_PATH="${ORT_DYLIB_PATH:-$PWD/.deps/onnxruntime/libonnxruntime.so.1.31.1}"
export PNTR_FUZZ_SECONDS="${1:-60}"
cargo test -p pntr-tests --test fuzz_inputs -- --nocapture --test-threads 2
cargo test -p pntr-cli --test register mutated_csv -- --nocapture
