#!/usr/bin/env bash
# `make test-cluster`: the shard scripts on a real Slurm. Installs Debian's
# slurm-wlm and munge if missing, starts a one-node cluster on this machine
# (slurmctld and slurmd on loopback, with a config written here under a
# temporary folder), submits a sharded render and a sharded data set with
# tools/slurm/submit.sh, waits for the merge jobs, compares the merged files
# with single-machine runs byte for byte, and shuts everything down (also
# on failure). Needs root or sudo. Not part of `make test`.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
cd "$root"
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
say() { echo "test-cluster: $*"; }
fail() {
  echo "test-cluster: FAILED: $*" >&2
  exit 1
}

need=()
command -v slurmctld >/dev/null || need+=(slurm-wlm)
command -v munged >/dev/null || need+=(munge)
if [ ${#need[@]} -gt 0 ]; then
  say "installing ${need[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null
fi

work="$(mktemp -d /tmp/nppp-slurm.XXXXXX)"
chmod 755 "$work"
cleanup() {
  local status=$?
  set +e
  if [ "$status" -ne 0 ]; then
    for log in "$work"/*.log; do
      echo "--- $log" >&2
      tail -15 "$log" >&2
    done
  fi
  if [ -n "${SLURM_CONF:-}" ]; then
    scancel --quiet --user "$(id -un)" 2>/dev/null
  fi
  # Every daemon this script started wrote a pid file into the work folder.
  local pids=()
  for f in "$work"/*.pid; do
    [ -f "$f" ] && pids+=("$($SUDO cat "$f")")
  done
  for p in "${pids[@]}"; do
    $SUDO kill "$p" 2>/dev/null
  done
  sleep 1
  for p in "${pids[@]}"; do
    $SUDO kill -9 "$p" 2>/dev/null
  done
  say "cluster stopped; logs were in $work (removed)"
  rm -rf "$work"
}
trap cleanup EXIT

# munge: this machine's key, or a new one in the work folder.
munge_sock="$work/munge.socket"
key="$work/munge.key"
$SUDO mungekey --create --keyfile="$key" --force 2>/dev/null \
  || $SUDO dd if=/dev/urandom of="$key" bs=1 count=1024 status=none
$SUDO chmod 600 "$key"
mkdir -p "$work/munge"
$SUDO munged --force --key-file="$key" --socket="$munge_sock" \
  --pid-file="$work/munge.pid" --log-file="$work/munged.log" --seed-file="$work/munge.seed"
sleep 1

host="$(hostname -s)"
user="$(id -un)"
cpus="$(nproc)"
mem_mb=$(($(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 512))
mkdir -p "$work/state" "$work/spool"
export SLURM_CONF="$work/slurm.conf"
cat >"$SLURM_CONF" <<CONF
ClusterName=nppp-test
SlurmctldHost=$host(127.0.0.1)
SlurmUser=$user
SlurmdUser=root
SlurmctldPort=16817
SlurmdPort=16818
AuthType=auth/munge
AuthInfo=socket=$munge_sock
CredType=cred/munge
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool
SlurmctldPidFile=$work/slurmctld.pid
SlurmdPidFile=$work/slurmd.pid
SlurmctldLogFile=$work/slurmctld.log
SlurmdLogFile=$work/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
MpiDefault=none
ReturnToService=2
SchedulerType=sched/backfill
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=nppp Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF

say "starting slurmctld and slurmd ($host, $cpus CPUs)"
$SUDO env SLURM_CONF="$SLURM_CONF" slurmctld -c -i
$SUDO env SLURM_CONF="$SLURM_CONF" slurmd -N "$host"
sleep 2
for _ in $(seq 60); do
  sinfo -h -o '%T' 2>/dev/null | grep -qE '^(idle|mixed|allocated)' && break
  sleep 1
done
sinfo -h -o '%T' | grep -qE '^idle' || {
  tail -20 "$work/slurmctld.log" "$work/slurmd.log" >&2
  fail "the node did not come up"
}
say "cluster up: $(sinfo -h -o '%P %D %T %c')"

bin="${NPPP:-}"
if [ -z "$bin" ]; then
  say "building nppp (release)"
  cargo build --release -q -p nppp-cli
  bin="${CARGO_TARGET_DIR:-$root/target}/release/nppp"
fi
export NPPP="$bin"

out="$work/out"
mkdir -p "$out"
scene=data/scenes/cornell-box.json
render_flags=(--width 48 --spp 8 --estimators neural --min-bounces 1)
gen_flags=(--mesh builtin --material white --rays 12000 --k 4 --seed 11)

say "single-machine runs"
"$bin" render "$scene" --quiet "${render_flags[@]}" --out "$out/single.exr"
"$bin" gen "${gen_flags[@]}" --quiet --out "$out/single.nppd" >/dev/null

say "submitting"
cd "$out"
r=$("$here/submit.sh" render 4 "$root/$scene" "$out/sharded.exr" "${render_flags[@]}")
echo "  $r"
g=$("$here/submit.sh" gen 3 "$out/sharded.nppd" "${gen_flags[@]}")
echo "  $g"
jobs=$(echo "$r $g" | grep -oE 'job [0-9]+' | awk '{print $2}' | tr '\n' ',')
for i in $(seq 600); do
  left=$(squeue -h -j "${jobs%,}" 2>/dev/null | wc -l)
  [ "$left" -eq 0 ] && break
  [ $((i % 10)) -eq 0 ] && say "waiting: $left jobs queued or running"
  sleep 1
done
[ "$left" -eq 0 ] || fail "jobs still queued after 10 minutes: $(squeue -h)"
for f in slurm-*.out; do
  if grep -q "^error" "$f"; then
    cat "$f" >&2
    fail "a job failed ($f)"
  fi
done
[ -f "$out/sharded.exr" ] || { cat slurm-*.out >&2; fail "the render merge wrote no image"; }
[ -f "$out/sharded.nppd" ] || { cat slurm-*.out >&2; fail "the data merge wrote no file"; }
cmp "$out/single.exr" "$out/sharded.exr" || fail "4 render shards merged differ from the single render"
cmp "$out/single.nppd" "$out/sharded.nppd" || fail "3 data shards merged differ from the single run"
say "render: 4 shards merged = single render, byte for byte ($(stat -c %s "$out/sharded.exr") bytes)"
say "data: 3 shards merged = single run, byte for byte ($(stat -c %s "$out/sharded.nppd") bytes)"
say "passed"
