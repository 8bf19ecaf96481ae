#!/usr/bin/env bash
# A single-node Slurm cluster on this machine, for the cluster tests and for
# trying `microray cluster` by hand (issue 18; docs/scale.md). Debian 12's
# slurm-wlm and munge (scripts/setup.sh installs them), run as root without
# systemd: munged, slurmctld and slurmd on localhost, with their
# configuration, state and logs in one folder.
#
#   scripts/slurm-local.sh start DIR   writes DIR/slurm.conf, starts the
#                                      daemons, waits until the node is idle;
#                                      prints the SLURM_CONF=... line to use
#   scripts/slurm-local.sh stop DIR    stops them (and any job left)
#
# Commands (sbatch, squeue, sacct, scontrol) find the cluster through
# SLURM_CONF=DIR/slurm.conf. Each DIR is a cluster of its own: its own
# munged (socket, pid, seed and log named after DIR under munge's folders),
# its own two ports, and stop ends only its own job steps, so two clusters
# (two test runs) on one machine do not stop each other. Finished tasks are recorded by jobcomp/filetxt
# (DIR/jobcomp.txt), which `sacct --completion` reads: no slurmdbd needed.
set -euo pipefail
trap 'echo "slurm-local: failed at line $LINENO: $BASH_COMMAND" >&2' ERR
cmd=${1:-}
dir=${2:-}
if [ -z "$cmd" ] || [ -z "$dir" ]; then
  echo "usage: $0 start|stop DIR" >&2
  exit 2
fi
mkdir -p "$dir"
dir=$(cd "$dir" && pwd)
conf="$dir/slurm.conf"

# this cluster's munge files (munged runs as munge: they go where it may write)
id=$(printf '%s' "$dir" | cksum | cut -d' ' -f1)
munge_socket=/run/munge/microray-$id.socket
munge_pid=/run/munge/microray-$id.pid

stop() {
  for pidfile in "$dir/slurmd.pid" "$dir/slurmctld.pid" "$dir/munged.pid"; do
    [ -f "$pidfile" ] || continue
    pid=$(cat "$pidfile")
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    kill -9 "$pid" 2>/dev/null || true
    rm -f "$pidfile"
  done
  # job steps this node daemon left behind (they carry its SLURM_CONF)
  for pid in $(pgrep -f "slurmstepd: \[" || true); do
    if tr '\0' '\n' <"/proc/$pid/environ" 2>/dev/null | grep -qxF "SLURM_CONF=$conf"; then
      kill -9 "$pid" 2>/dev/null || true
    fi
  done
  rm -f "$munge_socket" "$munge_socket.lock" "$munge_pid"
}

# A port no TCP socket of the machine holds (listening, connected or in
# TIME_WAIT: /proc/net/tcp*), from $1 on.
free_port() {
  local p=$1 tables=()
  for t in /proc/net/tcp /proc/net/tcp6; do [ -r "$t" ] && tables+=("$t"); done
  while awk -v port="$(printf '%04X' "$p")" 'FNR > 1 { split($2, a, ":"); if (a[2] == port) found = 1 }
                                             END { exit !found }' "${tables[@]}"; do
    p=$((p + 1))
  done
  echo "$p"
}

case "$cmd" in
stop)
  stop
  exit 0
  ;;
start) ;;
*)
  echo "usage: $0 start|stop DIR" >&2
  exit 2
  ;;
esac

if [ "$(id -u)" -ne 0 ]; then
  echo "slurm-local: needs root (munged runs as the munge user, the Slurm daemons as root)" >&2
  exit 1
fi
for tool in munged slurmctld slurmd sbatch sinfo; do
  command -v "$tool" >/dev/null 2>&1 || {
    echo "slurm-local: $tool is missing: install slurm-wlm and munge (scripts/setup.sh)" >&2
    exit 1
  }
done
stop

# munge: a key owned by munge, mode 400, and its socket folder
if [ ! -s /etc/munge/munge.key ]; then
  mkdir -p /etc/munge
  dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
fi
chown munge:munge /etc/munge /etc/munge/munge.key
chmod 700 /etc/munge
chmod 400 /etc/munge/munge.key
mkdir -p /run/munge /var/lib/munge /var/log/munge
chown munge:munge /run/munge /var/lib/munge /var/log/munge
# (munged runs as munge: its pid and log go where munge may write)
runuser -u munge -- munged --socket="$munge_socket" --pid-file="$munge_pid" \
  --seed-file="/var/lib/munge/microray-$id.seed" --log-file="/var/log/munge/microray-$id.log" --force
# (munged may return before it has written its pid)
for _ in $(seq 50); do [ -s "$munge_pid" ] && break; sleep 0.1; done
cp "$munge_pid" "$dir/munged.pid"
# below the kernel's ephemeral range (32768 on), where outgoing connections
# take their ports
ctld_port=$(free_port $((20000 + id % 6000 * 2)))
slurmd_port=$(free_port $((ctld_port + 1)))

cpus=$(nproc)
mem=$(awk '/MemTotal/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)
mkdir -p "$dir/state" "$dir/spool"
cat >"$conf" <<EOF
ClusterName=microray-local
SlurmctldHost=localhost
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$munge_socket
SlurmctldPort=$ctld_port
SlurmdPort=$slurmd_port
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
MpiDefault=none
ReturnToService=2
JobRequeue=1
SchedulerType=sched/backfill
SchedulerParameters=sched_interval=1
JobCompType=jobcomp/filetxt
JobCompLoc=$dir/jobcomp.txt
AccountingStorageType=accounting_storage/none
InactiveLimit=0
KillWait=5
MinJobAge=600
NodeName=localhost CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=local Nodes=localhost Default=YES MaxTime=INFINITE State=UP OverSubscribe=YES
EOF
export SLURM_CONF="$conf"
slurmctld -f "$conf" -i 2>>"$dir/slurmctld.log"
slurmd -f "$conf" -N localhost 2>>"$dir/slurmd.log"
for _ in $(seq 150); do
  state=$(sinfo -h -N -o '%T' 2>/dev/null | head -n 1)
  case "$state" in
  idle*|mixed*|allocated*)
    echo "SLURM_CONF=$conf"
    exit 0
    ;;
  esac
  sleep 0.2
done
echo "slurm-local: the node did not become idle within 30 s (state '${state:-none}'); logs in $dir" >&2
tail -n 20 "$dir/slurmctld.log" "$dir/slurmd.log" >&2 || true
exit 1
