# Helpers of the Slurm scripts (sourced).

die() {
  echo "error: $*" >&2
  exit 1
}

# The nppp binary: $NPPP, else `nppp` on the PATH, else this checkout's
# release build.
nppp_bin() {
  if [ -n "${NPPP:-}" ]; then
    echo "$NPPP"
  elif command -v nppp >/dev/null; then
    command -v nppp
  else
    local root
    root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
    for b in "${CARGO_TARGET_DIR:-$root/target}/release/nppp" "$root/target/release/nppp"; do
      [ -x "$b" ] && { echo "$b"; return; }
    done
    die "no nppp binary: set NPPP, put nppp on the PATH, or run make build"
  fi
}

# "I K" of this array task: the task's index and the array's size. The
# array must be 0-(K-1) (a step or a list would leave shards out).
array_task() {
  [ -n "${SLURM_ARRAY_TASK_ID:-}" ] || die "not a job-array task: submit with sbatch --array=0-(K-1)"
  local min="${SLURM_ARRAY_TASK_MIN:-0}" max="${SLURM_ARRAY_TASK_MAX:?}"
  local count="${SLURM_ARRAY_TASK_COUNT:-$((max - min + 1))}"
  [ "$min" -eq 0 ] && [ "$count" -eq $((max + 1)) ] \
    || die "the array must be 0-(K-1) without steps or gaps (it is $min-$max, $count tasks)"
  echo "$SLURM_ARRAY_TASK_ID $count"
}
