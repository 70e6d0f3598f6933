#!/usr/bin/env bash
# Stop the cluster tests/slurm/up.sh started (its daemons, by their pid files), and munged.
# Its state (the accounting database, logs) stays in $SLURM_TEST_DIR for a look afterwards.
set -uo pipefail
DIR=${SLURM_TEST_DIR:-/tmp/hds-slurm}
for pidfile in "$DIR/slurmd.pid" "$DIR/slurmctld.pid" "$DIR/slurmdbd.pid" "$DIR/mysql.pid" \
        /run/munge/munged.pid; do
    [ -s "$pidfile" ] && kill "$(cat "$pidfile")" 2>/dev/null
done
rm -f /etc/slurm/slurm.conf /etc/slurm/slurmdbd.conf
exit 0
