#!/usr/bin/env bash
# A single-node SLURM on this machine, for trying the sweep launchers (conf/hydra/launcher/) and for CI.
#   scripts/slurm_local.sh install        # Debian's slurm-wlm and munge, when missing (needs root and apt-get)
#   scripts/slurm_local.sh up   [DIR]     # install if needed, write DIR/slurm.conf, start munged, slurmctld, slurmd
#   export SLURM_CONF=DIR/slurm.conf      # then sbatch, squeue and hydra/launcher=slurm_cpu use it
#   scripts/slurm_local.sh down [DIR]     # stop the three daemons by their pid files
# DIR (default $SLURM_LOCAL_DIR or /tmp/realityavatar-slurm) holds the config, munge key and socket, state, pid files
# and logs; nothing is written under /etc. One partition, `debug` (the default), with the host's cores and memory;
# select/cons_tres, accounting off, so `sacct` fails and submitit logs "Bypassing sacct error": it then learns that
# a job ended from the result file the job writes. Exit status 3: SLURM cannot be brought up here (the reason on
# stderr), which the tests turn into a skip.
set -euo pipefail
CMD=${1:-}
DIR=$(realpath -m "${2:-${SLURM_LOCAL_DIR:-/tmp/realityavatar-slurm}}")
PORT=${SLURM_LOCAL_PORT:-6817}  # slurmctld; slurmd takes the next one
DAEMONS=(slurmd slurmctld munged)  # stopped in this order

unavailable() { echo "slurm_local: $*" >&2; exit 3; }

install() {
  command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v munged >/dev/null && return 0
  command -v apt-get >/dev/null || unavailable "slurm-wlm and munge are not installed and there is no apt-get"
  local sudo=""
  if [ "$(id -u)" -ne 0 ]; then
    sudo -n true 2>/dev/null || unavailable "slurm-wlm and munge are not installed and apt-get needs root (no sudo -n)"
    sudo="sudo -n"
  fi
  echo "slurm_local: installing slurm-wlm and munge" >&2
  export DEBIAN_FRONTEND=noninteractive
  { $sudo apt-get update -qq && $sudo apt-get install -y -qq --no-install-recommends slurm-wlm munge; } >/dev/null \
    || unavailable "apt-get install slurm-wlm munge failed"
}

running() { [ -f "$DIR/$1.pid" ] && kill -0 "$(cat "$DIR/$1.pid")" 2>/dev/null; }

wait_for() {  # wait_for SECONDS WHAT COMMAND...
  local t=$1 what=$2; shift 2
  for _ in $(seq $((t * 5))); do "$@" >/dev/null 2>&1 && return 0; sleep 0.2; done
  echo "slurm_local: $what did not come up in $t s; its log:" >&2
  tail -n 20 "$DIR/$what.log" >&2 || true
  down; exit 1
}

write_conf() {
  local host user node
  host=$(hostname -s)
  user=$(id -un)
  # the node line as slurmd sees this machine (CPUs, sockets, cores, threads, RealMemory)
  node=$(slurmd -C | head -n 1 | sed "s/^NodeName=[^ ]*/NodeName=$host NodeAddr=127.0.0.1/")
  cat >"$DIR/slurm.conf" <<EOF
ClusterName=local
SlurmctldHost=$host(127.0.0.1)
SlurmctldPort=$PORT
SlurmdPort=$((PORT + 1))
SlurmUser=$user
SlurmdUser=$user
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$DIR/munge.socket
StateSaveLocation=$DIR/ctld
SlurmdSpoolDir=$DIR/d
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/slurmctld.log
SlurmdLogFile=$DIR/slurmd.log
PlugStackConfig=$DIR/plugstack.conf
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
ReturnToService=2
$node State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
  : >"$DIR/plugstack.conf"
}

up() {
  install
  if running slurmctld || running slurmd || running munged; then down; fi
  mkdir -p "$DIR/ctld" "$DIR/d"
  chmod 700 "$DIR"  # munged refuses a key or socket in a directory others can write to
  [ -f "$DIR/munge.key" ] || mungekey --create --keyfile="$DIR/munge.key"
  chmod 600 "$DIR/munge.key"
  write_conf
  export SLURM_CONF="$DIR/slurm.conf"
  # --force: munged otherwise refuses to run as root; the key and socket are this directory's own
  munged --force --key-file="$DIR/munge.key" --socket="$DIR/munge.socket" --pid-file="$DIR/munged.pid" \
    --log-file="$DIR/munged.log" --seed-file="$DIR/munged.seed" 2>>"$DIR/munged.log" \
    || { tail -n 5 "$DIR/munged.log" >&2; exit 1; }
  slurmctld -f "$SLURM_CONF" -i
  slurmd -f "$SLURM_CONF" -N "$(hostname -s)"
  wait_for 30 slurmctld scontrol ping
  wait_for 30 slurmd bash -c "sinfo -h -N -o %T | grep -qx idle"
  echo "slurm_local: up ($(sinfo -h -o '%P %D node(s), %c CPUs, %m MB')); export SLURM_CONF=$SLURM_CONF" >&2
}

down() {
  if running slurmctld && running slurmd; then  # jobs first: with proctrack/linuxproc a job outlives slurmd
    export SLURM_CONF="$DIR/slurm.conf"
    scancel -u "$(id -un)" 2>/dev/null || true
    for _ in $(seq 50); do [ -z "$(squeue -h -o %i 2>/dev/null)" ] && break; sleep 0.2; done
  fi
  for d in "${DAEMONS[@]}"; do
    running "$d" || continue
    local pid
    pid=$(cat "$DIR/$d.pid")
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
    kill -0 "$pid" 2>/dev/null && kill -9 "$pid" 2>/dev/null || true
    rm -f "$DIR/$d.pid"
  done
}

case "$CMD" in
  install) install ;;
  up) up ;;
  down) down; echo "slurm_local: down ($DIR)" >&2 ;;
  *) echo "usage: $0 install | up [DIR] | down [DIR]" >&2; exit 2 ;;
esac
