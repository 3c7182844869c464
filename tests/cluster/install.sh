#!/usr/bin/env bash
# Debian's SLURM and munge for the cluster test (make test-cluster), installed only when missing.
set -euo pipefail
needed=()
for pair in slurmctld:slurmctld slurmd:slurmd sinfo:slurm-client munged:munge; do
    command -v "${pair%%:*}" >/dev/null 2>&1 || [ -x "/usr/sbin/${pair%%:*}" ] || needed+=("${pair#*:}")
done
if [ ${#needed[@]} -gt 0 ]; then
    echo "installing ${needed[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${needed[@]}" >/dev/null
fi
[ -s /etc/munge/munge.key ] || { mkdir -p /etc/munge; dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none;
                                 chown munge:munge /etc/munge/munge.key; chmod 400 /etc/munge/munge.key; }
