"""A real single-node SLURM cluster on localhost for the cluster test (``make test-cluster``).

Debian's slurmctld, slurmd and munge (``tests/cluster/install.sh`` installs them when missing) run as
child processes in the foreground, so every daemon this module starts is stopped by its PID, also
when the test fails. The configuration is the minimal one ../shared/NOTES.md records for this machine
kind: no accounting (the executor plugin then polls ``squeue``), linuxproc process tracking, no task
plugin, cores and memory as consumable resources. It has to be ``/etc/slurm/slurm.conf``: the executor
plugin strips ``SLURM_*`` variables before its inner ``srun``. A file already there is put back
afterwards.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import shutil
import subprocess
import time
from pathlib import Path

CONF = Path("/etc/slurm/slurm.conf")
DAEMONS = ("munged", "slurmctld", "slurmd", "sinfo", "squeue", "sbatch", "srun")


def slurm_conf(cpus: int, memory_mb: int, state: Path) -> str:
    """A minimal slurm.conf for one node called localhost with ``cpus`` cores and ``memory_mb`` of memory."""
    return f"""ClusterName=facetsynth-test
SlurmctldHost=localhost
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
MinJobAge=300
ReturnToService=2
StateSaveLocation={state}/ctld
SlurmdSpoolDir={state}/d
SlurmctldPidFile={state}/slurmctld.pid
SlurmdPidFile={state}/slurmd.pid
SlurmctldLogFile={state}/slurmctld.log
SlurmdLogFile={state}/slurmd.log
NodeName=localhost CPUs={cpus} RealMemory={memory_mb} State=UNKNOWN
PartitionName=main Nodes=localhost Default=YES MaxTime=INFINITE State=UP
"""


def missing() -> list[str]:
    """The SLURM and munge programs that are not installed."""
    return [name for name in DAEMONS if shutil.which(name) is None and not Path("/usr/sbin", name).exists()]


def _wait(predicate, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.25)
    raise RuntimeError(f"local SLURM: {what} within {timeout:.0f} s")


def _node_state() -> str:
    done = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True)
    return done.stdout.strip() if done.returncode == 0 else ""


@contextlib.contextmanager
def local_slurm(state: Path, cpus: int | None = None, memory_mb: int = 16000):
    """Start munged, slurmctld and slurmd for one node on localhost; stop them by PID on exit.

    ``state``: a fresh folder for the daemons' state, spool and logs (their logs stay there). Yields the
    PIDs of the daemons it started (a munged already running is used, and left running).
    """
    absent = missing()
    if absent:
        raise RuntimeError(f"local SLURM: not installed: {', '.join(absent)} (run tests/cluster/install.sh)")
    state = Path(state)
    for sub in ("ctld", "d", "munge"):
        (state / sub).mkdir(parents=True, exist_ok=True)
    cpus = cpus or os.cpu_count() or 1
    backup = CONF.read_bytes() if CONF.exists() else None
    CONF.parent.mkdir(parents=True, exist_ok=True)
    CONF.write_text(slurm_conf(cpus, memory_mb, state))
    started: list[subprocess.Popen] = []
    try:
        socket_dir = Path("/run/munge")
        socket_dir.mkdir(parents=True, exist_ok=True)
        munge = pwd.getpwnam("munge")
        os.chown(socket_dir, munge.pw_uid, munge.pw_gid)
        socket_dir.chmod(0o755)
        if subprocess.run(["munge", "-n"], capture_output=True).returncode != 0:    # no munged running yet
            started.append(subprocess.Popen(["runuser", "-u", "munge", "--", "munged", "-F", "--force"],
                                            stdout=open(state / "munge/munged.log", "w"), stderr=subprocess.STDOUT))
            _wait(lambda: subprocess.run(["munge", "-n"], capture_output=True).returncode == 0, 20, "munged answers")
        logs = {name: open(state / f"{name}.out", "w") for name in ("slurmctld", "slurmd")}
        started.append(subprocess.Popen(["slurmctld", "-D", "-i"], stdout=logs["slurmctld"], stderr=subprocess.STDOUT))
        started.append(subprocess.Popen(["slurmd", "-D", "-N", "localhost"], stdout=logs["slurmd"],
                                        stderr=subprocess.STDOUT))
        _wait(lambda: _node_state() == "idle", 60, "the node becomes idle")
        yield [process.pid for process in started]
    finally:
        for process in reversed(started):
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
        if backup is None:
            CONF.unlink(missing_ok=True)
        else:
            CONF.write_bytes(backup)
