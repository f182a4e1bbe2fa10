#!/usr/bin/env bash
# One shard of training data, as one task of a Slurm job array:
#
#   sbatch --array=0-3 tools/slurm/gen-shard.sh PARTS_DIR nppp-gen-flags...
#
# Task I of the K tasks traces the I-th of K ranges of the input rays (whole
# chunks of 4096 rays: `nppp gen FLAGS --shard I/K`) into
# PARTS_DIR/part-I.nppd. tools/slurm/merge.sh then merges the parts into the
# .nppd file one run would have written, byte for byte. The flags are
# `nppp gen`'s without --out, e.g. --scene data/scenes/cornell-box.json
# --instance 0 --rays 200000. tools/slurm/submit.sh does both submissions.
#SBATCH --job-name=nppp-gen
#SBATCH --output=slurm-%A_%a.out
set -euo pipefail
here="${NPPP_SLURM_DIR:-$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)}"
# Under Slurm the script runs from a spool copy: submit.sh says where the
# scripts are; else they are looked for under the submit directory.
[ -f "$here/common.sh" ] || here="${SLURM_SUBMIT_DIR:-.}/tools/slurm"
# shellcheck source=common.sh
source "$here/common.sh"
[ $# -ge 2 ] || die "usage: sbatch --array=0-(K-1) $0 PARTS_DIR nppp-gen-flags..."
parts="$1"
shift
read -r index count < <(array_task)
mkdir -p "$parts"
exec "$(nppp_bin)" gen "$@" --quiet --overwrite --shard "$index/$count" --out "$parts/part-$index.nppd"
