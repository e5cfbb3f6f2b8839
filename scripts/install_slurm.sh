#!/usr/bin/env bash
# Install a minimal single-node SLURM (controller + compute daemon + client tools) and
# munge from Debian packages, for scripts/local_slurm.py and tests/workflow/test_slurm.py.
#
# Idempotent: does nothing when every tool is already installed. Needs root (apt-get).
# Debian 12 ships Slurm 22.05: `slurmctld`, `slurmd` and `slurm-client` are the three
# packages behind the `slurm-wlm` metapackage; `munge` provides munged and the key tools.
set -euo pipefail

PACKAGES=(slurmctld slurmd slurm-client munge)
TOOLS=(slurmctld slurmd sbatch squeue sinfo scancel srun munged mungekey)

missing=0
for tool in "${TOOLS[@]}"; do
    if ! command -v "$tool" >/dev/null 2>&1 && [ ! -x "/usr/sbin/$tool" ]; then
        missing=1
    fi
done
if [ "$missing" -eq 0 ]; then
    echo "install_slurm.sh: already installed: $(dpkg-query -W -f '${Package} ${Version}  ' "${PACKAGES[@]}" 2>/dev/null)"
    exit 0
fi

if [ "$(id -u)" -ne 0 ]; then
    echo "install_slurm.sh: needs root for apt-get (missing SLURM/munge tools)" >&2
    exit 1
fi

export DEBIAN_FRONTEND=noninteractive

# Keep the package scripts from starting the daemons as system services: the
# cluster used by the tests is started (and stopped) by scripts/local_slurm.py.
# Only install a policy-rc.d if none exists, and remove only the one we created.
created_policy=0
if [ ! -e /usr/sbin/policy-rc.d ]; then
    printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d
    chmod 755 /usr/sbin/policy-rc.d
    created_policy=1
fi
cleanup() {
    if [ "$created_policy" -eq 1 ]; then rm -f /usr/sbin/policy-rc.d; fi
}
trap cleanup EXIT

apt-get update
apt-get install -y --no-install-recommends "${PACKAGES[@]}"

echo "install_slurm.sh: installed: $(dpkg-query -W -f '${Package} ${Version}  ' "${PACKAGES[@]}")"
