#!/usr/bin/env bash
# Submits a sharded render or data set to Slurm: a job array of K shards and
# a merge job that runs when all of them succeeded.
#
#   tools/slurm/submit.sh render K SCENE OUT.exr [nppp render flags...]
#   tools/slurm/submit.sh gen K OUT.nppd nppp-gen-flags...
#
# Parts go to OUT.parts/ beside OUT. Extra sbatch options (partition, time,
# CPUs per task) come from $SBATCH_OPTS, e.g. SBATCH_OPTS="-p farm -c 16".
# Prints the two job IDs.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
# shellcheck source=common.sh
source "$here/common.sh"
# The jobs run copies of the scripts; they find common.sh and the checkout here.
export NPPP_SLURM_DIR="$here"
usage="usage: $0 render K SCENE OUT.exr [render flags...] | $0 gen K OUT.nppd gen-flags..."
[ $# -ge 3 ] || die "$usage"
kind="$1" k="$2"
shift 2
[[ "$k" =~ ^[1-9][0-9]*$ ]] || die "K = $k: give a whole number of shards, at least 1"
# shellcheck disable=SC2206
opts=(${SBATCH_OPTS:-})
case "$kind" in
  render)
    [ $# -ge 2 ] || die "$usage"
    scene="$1" out="$2"
    shift 2
    parts="$out.parts"
    array=$(sbatch --parsable "${opts[@]}" --array="0-$((k - 1))" "$here/render-shard.sh" "$scene" "$parts" "$@")
    ;;
  gen)
    out="$1"
    shift
    parts="$out.parts"
    array=$(sbatch --parsable "${opts[@]}" --array="0-$((k - 1))" "$here/gen-shard.sh" "$parts" "$@")
    ;;
  *) die "$usage" ;;
esac
array="${array%%;*}"
merge=$(sbatch --parsable "${opts[@]}" --dependency="afterok:$array" "$here/merge.sh" "$parts" "$out")
echo "shards: job $array (array 0-$((k - 1))), merge: job ${merge%%;*} -> $out"
