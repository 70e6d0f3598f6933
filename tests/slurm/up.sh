#!/usr/bin/env bash
# A single-node SLURM cluster on this machine, for `make test-slurm`: Debian's slurm-wlm, munge,
# slurmdbd and mariadb-server (installed here if missing), the controller, the one compute node
# and the accounting daemon on localhost, run as root, state under $SLURM_TEST_DIR (default
# /tmp/hds-slurm). Accounting is what submitit reads a job's state from (sacct): without it a
# cancelled job is never seen to end. Idempotent: a cluster already up (sinfo and sacct
# answer) is left as it is. tests/slurm/down.sh stops it.
set -euo pipefail
[ "$(id -u)" = 0 ] || { echo "error: tests/slurm/up.sh installs and starts daemons: run it as root" >&2; exit 2; }
DIR=${SLURM_TEST_DIR:-/tmp/hds-slurm}

if ! command -v slurmctld >/dev/null || ! command -v slurmdbd >/dev/null \
        || ! command -v munged >/dev/null || ! command -v mariadbd >/dev/null; then
    echo "installing slurm-wlm, slurmdbd, munge and mariadb-server (apt-get)"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm slurmdbd munge \
        mariadb-server >/dev/null
fi

if sinfo -h >/dev/null 2>&1 && sacct -n -X >/dev/null 2>&1 && [ -f "$DIR/slurm.conf" ]; then
    echo "slurm is up: $(sinfo -h -o '%P %D %t' | head -1)"
    exit 0
fi

mkdir -p "$DIR"/{ctld,spool,log,db} /etc/slurm /run/munge /var/log/munge /var/lib/munge /etc/munge
# munge: its key (Debian's package makes one; a bare image may not have it), its daemon
if [ ! -s /etc/munge/munge.key ]; then
    dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
fi
chown -R munge:munge /etc/munge /run/munge /var/log/munge /var/lib/munge
chmod 0700 /etc/munge && chmod 0400 /etc/munge/munge.key
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    runuser -u munge -- /usr/sbin/munged
    for _ in $(seq 50); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.1; done
fi

# accounting: a MariaDB of our own (its data, socket and port 3307 under $DIR), slurmdbd on it
if [ ! -d "$DIR/db/mysql" ]; then
    mariadb-install-db --datadir="$DIR/db" --user=root --auth-root-authentication-method=socket \
        >"$DIR/log/mariadb-install.log" 2>&1
fi
if ! mariadb --socket="$DIR/mysql.sock" -e 'select 1' >/dev/null 2>&1; then
    mariadbd --datadir="$DIR/db" --socket="$DIR/mysql.sock" --port=3307 \
        --bind-address=127.0.0.1 --user=root --pid-file="$DIR/mysql.pid" \
        --log-error="$DIR/log/mariadb.log" &
    for _ in $(seq 100); do
        mariadb --socket="$DIR/mysql.sock" -e 'select 1' >/dev/null 2>&1 && break; sleep 0.2
    done
fi
mariadb --socket="$DIR/mysql.sock" <<SQL
CREATE USER IF NOT EXISTS 'slurm'@'127.0.0.1' IDENTIFIED BY 'hds-test';
CREATE DATABASE IF NOT EXISTS slurm_acct_db;
GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';
SQL
cat > "$DIR/slurmdbd.conf" <<CONF
AuthType=auth/munge
DbdHost=localhost
DbdPort=6819
SlurmUser=root
PidFile=$DIR/slurmdbd.pid
LogFile=$DIR/log/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort=3307
StorageUser=slurm
StoragePass=hds-test
StorageLoc=slurm_acct_db
CONF
chmod 600 "$DIR/slurmdbd.conf"
ln -sf "$DIR/slurmdbd.conf" /etc/slurm/slurmdbd.conf
if ! sacctmgr -n list cluster >/dev/null 2>&1; then
    /usr/sbin/slurmdbd
    for _ in $(seq 100); do sacctmgr -n list cluster >/dev/null 2>&1 && break; sleep 0.2; done
fi
sacctmgr -i add cluster hds-test >/dev/null 2>&1 || true  # already there on a second start

NODE=$(hostname -s)
CPUS=$(nproc)
MEM_MB=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 1024 ))
# No cgroups (a container may not delegate them): processes tracked by their parent ids,
# memory not enforced; cons_tres hands out single cores, so two 1-CPU jobs run side by side.
cat > "$DIR/slurm.conf" <<CONF
ClusterName=hds-test
SlurmctldHost=$NODE(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$DIR/ctld
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
SlurmctldPort=6817
SlurmdPort=6818
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
AccountingStoragePort=6819
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
MpiDefault=none
ReturnToService=2
KillWait=5
MinJobAge=600
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=debug Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
CONF
ln -sf "$DIR/slurm.conf" /etc/slurm/slurm.conf

# a controller already running (started before accounting was configured) is restarted
for pidfile in "$DIR/slurmd.pid" "$DIR/slurmctld.pid"; do
    pid=$(cat "$pidfile" 2>/dev/null) || continue
    kill "$pid" 2>/dev/null || continue
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
done
/usr/sbin/slurmctld
/usr/sbin/slurmd
for _ in $(seq 100); do
    if sinfo -h -o '%t' 2>/dev/null | grep -qE '^(idle|mix|alloc)' && sacct -n -X >/dev/null 2>&1
    then
        echo "slurm is up: $(sinfo -h -o '%P %D %t %C')"
        exit 0
    fi
    sleep 0.2
done
echo "error: slurm did not come up; see $DIR/log/slurmctld.log and $DIR/log/slurmd.log" >&2
sinfo >&2 || true
exit 1
