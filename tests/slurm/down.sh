#!/usr/bin/env bash
# Stop the cluster tests/slurm/up.sh started (its daemons, by their pid files), and munged.
set -uo pipefail
DIR=${SLURM_TEST_DIR:-/tmp/hds-slurm}
for pidfile in "$DIR/slurmd.pid" "$DIR/slurmctld.pid" /run/munge/munged.pid; do
    [ -s "$pidfile" ] && kill "$(cat "$pidfile")" 2>/dev/null
done
rm -f /etc/slurm/slurm.conf
exit 0
