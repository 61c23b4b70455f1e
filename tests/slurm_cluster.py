"""A real single-node Slurm in a temporary folder, for the tests of `sked-batch --slurm`.

Debian's slurm-wlm and munge (`.ci/setup --for-tests` installs them): a munge daemon with its own key and
socket, slurmctld and slurmd on this host with state, spool, logs and pid files in the folder, proctrack by
/proc and no cgroups (containers have none to give), no accounting. Stopped by the pids in its pid files.
Needs root (slurmd runs jobs as their user); anything missing is a skip reason, never a failure.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path
from typing import Dict, Optional

DAEMONS = {"munged": "/usr/sbin/munged", "slurmctld": "/usr/sbin/slurmctld", "slurmd": "/usr/sbin/slurmd"}


def why_not() -> Optional[str]:
    """Why a Slurm cannot be started here (None: it can)."""
    missing = [name for name, path in DAEMONS.items() if not os.access(path, os.X_OK)]
    missing += [name for name in ("sbatch", "squeue", "scancel") if shutil.which(name) is None]
    if missing:
        return (f"Slurm is not installed ({', '.join(missing)} missing): `bash .ci/setup --for-tests` installs "
                "slurm-wlm and munge as root")
    if os.geteuid() != 0:
        return "starting slurmd needs root (it runs jobs as their user)"
    return None


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class SlurmCluster:
    """`with SlurmCluster(folder, cpus=2) as cluster:` ... `cluster.env` for sbatch, squeue, scancel."""

    def __init__(self, folder: Path, cpus: int = 2, memory_mb: int = 4000):
        self.folder = Path(folder)
        self.cpus, self.memory_mb = cpus, memory_mb
        self.host = socket.gethostname().split(".")[0]
        self.conf = self.folder / "slurm.conf"
        self.env: Dict[str, str] = {**os.environ, "SLURM_CONF": str(self.conf)}

    def _write_conf(self) -> None:
        f = self.folder
        lines = [
            "ClusterName=skedtest", f"SlurmctldHost={self.host}", f"SlurmctldPort={_free_port()}",
            f"SlurmdPort={_free_port()}", "AuthType=auth/munge", f"AuthInfo=socket={f / 'munge.socket'}",
            "CredType=cred/munge", "SlurmUser=root", "SlurmdUser=root", f"StateSaveLocation={f / 'state'}",
            f"SlurmdSpoolDir={f / 'spool'}", f"SlurmctldPidFile={f / 'slurmctld.pid'}", f"SlurmdPidFile={f / 'slurmd.pid'}",
            f"SlurmctldLogFile={f / 'slurmctld.log'}", f"SlurmdLogFile={f / 'slurmd.log'}",
            "ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none", "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_CPU", "SchedulerType=sched/builtin", "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none", "MpiDefault=none", "ReturnToService=2",
            "SchedulerParameters=sched_interval=2", "KillWait=5",
            f"NodeName={self.host} CPUs={self.cpus} RealMemory={self.memory_mb} State=UNKNOWN",
            "PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP",
        ]
        self.conf.write_text("\n".join(lines) + "\n")

    def start(self) -> "SlurmCluster":
        f = self.folder
        for sub in ("state", "spool"):
            (f / sub).mkdir(parents=True, exist_ok=True)
        key = f / "munge.key"
        key.write_bytes(os.urandom(128))
        key.chmod(0o400)
        self._write_conf()
        self._run([DAEMONS["munged"], "--force", f"--key-file={key}", f"--socket={f / 'munge.socket'}",
                   f"--pid-file={f / 'munged.pid'}", f"--log-file={f / 'munged.log'}", f"--seed-file={f / 'munge.seed'}"])
        self._run([DAEMONS["slurmctld"], "-f", str(self.conf)])
        self._run([DAEMONS["slurmd"], "-f", str(self.conf)])
        deadline = time.time() + 60
        while time.time() < deadline:  # the node registers with the controller
            result = subprocess.run(["sinfo", "-h", "-o", "%T"], env=self.env, capture_output=True, text=True)
            if result.returncode == 0 and result.stdout.strip() in ("idle", "mixed", "allocated"):
                return self
            time.sleep(0.5)
        raise RuntimeError(f"the Slurm node did not come up: {result.stdout} {result.stderr}; logs in {f}")

    def _run(self, command) -> None:
        result = subprocess.run(command, capture_output=True, text=True, timeout=60)
        if result.returncode != 0:
            self.stop()
            raise RuntimeError(f"{command[0]} did not start: {result.stderr.strip()} (logs in {self.folder})")

    def stop(self) -> None:
        """Its jobs cancelled, then each daemon by the pid in its pid file (slurmd first)."""
        if (self.folder / "slurmctld.pid").exists():
            subprocess.run(["scancel", "--me"], env=self.env, capture_output=True, timeout=60)
            for _ in range(60):  # the job steps end (KillWait) before their slurmd does
                queued = subprocess.run(["squeue", "--me", "-h"], env=self.env, capture_output=True, text=True)
                if queued.returncode != 0 or not queued.stdout.strip():
                    break
                time.sleep(0.5)
        for name in ("slurmd", "slurmctld", "munged"):
            pid_file = self.folder / f"{name}.pid"
            try:
                pid = int(pid_file.read_text().split()[0])
            except (OSError, ValueError, IndexError):
                continue
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                continue
            for _ in range(100):
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    break
                time.sleep(0.1)

    def __enter__(self) -> "SlurmCluster":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
