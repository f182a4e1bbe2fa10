#!/usr/bin/env bash
# One shard of a render, as one task of a Slurm job array:
#
#   sbatch --array=0-15 tools/slurm/render-shard.sh SCENE PARTS_DIR [nppp render flags...]
#
# Task I of the K tasks renders every pixel's I-th of K sample ranges
# (`nppp render SCENE --shard I/K`) into PARTS_DIR/part-I.nppr. Then
# tools/slurm/merge.sh (submitted with --dependency=afterok:JOB) merges the
# parts into the EXR one machine would have written, byte for byte.
# tools/slurm/submit.sh does both submissions. The binary is $NPPP, else
# `nppp` on the PATH, else target/release/nppp of this checkout.
#SBATCH --job-name=nppp-render
#SBATCH --output=slurm-%A_%a.out
set -euo pipefail
here="${NPPP_SLURM_DIR:-$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)}"
# Under Slurm the script runs from a spool copy: submit.sh says where the
# scripts are; else they are looked for under the submit directory.
[ -f "$here/common.sh" ] || here="${SLURM_SUBMIT_DIR:-.}/tools/slurm"
# shellcheck source=common.sh
source "$here/common.sh"
[ $# -ge 2 ] || die "usage: sbatch --array=0-(K-1) $0 SCENE PARTS_DIR [nppp render flags...]"
scene="$1" parts="$2"
shift 2
read -r index count < <(array_task)
mkdir -p "$parts"
exec "$(nppp_bin)" render "$scene" --quiet --shard "$index/$count" --out "$parts/part-$index.nppr" "$@"
