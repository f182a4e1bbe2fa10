#!/usr/bin/env bash
# Merges the parts of a job array (tools/slurm/render-shard.sh or
# gen-shard.sh) once every task has succeeded:
#
#   sbatch --dependency=afterok:JOB tools/slurm/merge.sh PARTS_DIR OUT [--png PREVIEW.png]
#
# OUT is an EXR for render parts (PARTS_DIR/*.nppr), an .nppd for data parts
# (PARTS_DIR/*.nppd). `nppp merge` refuses a missing, repeated or foreign part.
#SBATCH --job-name=nppp-merge
#SBATCH --output=slurm-%j.out
set -euo pipefail
here="${NPPP_SLURM_DIR:-$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)}"
# Under Slurm the script runs from a spool copy: submit.sh says where the
# scripts are; else they are looked for under the submit directory.
[ -f "$here/common.sh" ] || here="${SLURM_SUBMIT_DIR:-.}/tools/slurm"
# shellcheck source=common.sh
source "$here/common.sh"
[ $# -ge 2 ] || die "usage: sbatch --dependency=afterok:JOB $0 PARTS_DIR OUT [nppp merge flags...]"
parts="$1" out="$2"
shift 2
case "$out" in
  *.exr | *.EXR) ext=nppr ;;
  *.nppd | *.NPPD) ext=nppd ;;
  *) die "$out: name the merged file *.exr (render) or *.nppd (data)" ;;
esac
shopt -s nullglob
files=("$parts"/part-*."$ext")
[ ${#files[@]} -gt 0 ] || die "$parts holds no part-*.$ext files"
exec "$(nppp_bin)" merge "${files[@]}" --out "$out" "$@"
