"""A real one-node Slurm cluster on this machine, in a folder of its own (for the tests of the
slurm launcher, and to try a sweep's cluster path on a workstation).

    python scripts/slurm_cluster.py start DIR    # writes DIR/slurm.conf, starts munged, slurmctld, slurmd
    python scripts/slurm_cluster.py stop DIR     # stops them
    export SLURM_CONF=DIR/slurm.conf             # then sbatch, squeue, stdr-train hydra/launcher=slurm ...

Needs Debian's `slurm-wlm` and `munge` (`apt-get install slurm-wlm munge`) and root: the daemons
run as root with their state, spool, logs and munge socket under DIR, so nothing outside DIR
is changed. One node named after this host with all its cores, one partition `debug`,
ProctrackType=proctrack/linuxproc and TaskPlugin=task/none (no cgroups needed), ports chosen
free, and job credentials that expire after 15 s (cred_expire: a requeued job waits that long
before it starts again, 120 s by default). `start` waits until the node is idle and a job can run.
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

DAEMONS = ("slurmd", "slurmctld", "munged")
TOOLS = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "scontrol", "scancel", "sinfo")


def missing() -> str | None:
    """Why a cluster cannot be started here (None: it can)."""
    gone = [t for t in TOOLS if shutil.which(t) is None and not Path(f"/usr/sbin/{t}").exists()]
    if gone:
        return f"{', '.join(gone)} not installed (apt-get install slurm-wlm munge)"
    if os.geteuid() != 0:
        return "the test cluster's daemons run as root"
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _tool(name: str) -> str:
    return shutil.which(name) or f"/usr/sbin/{name}"


def conf_text(d: Path, host: str, cpus: int, mem_mb: int, ctld_port: int, d_port: int) -> str:
    return f"""# a one-node test cluster (scripts/slurm_cluster.py)
ClusterName=stdrtest
SlurmctldHost={host}
SlurmUser=root
SlurmdUser=root
SlurmctldPort={ctld_port}
SlurmdPort={d_port}
AuthType=auth/munge
AuthInfo=socket={d / 'munge' / 'munge.socket'},cred_expire=15
CredType=cred/munge
StateSaveLocation={d / 'state'}
SlurmdSpoolDir={d / 'spool'}
SlurmctldPidFile={d / 'slurmctld.pid'}
SlurmdPidFile={d / 'slurmd.pid'}
SlurmctldLogFile={d / 'slurmctld.log'}
SlurmdLogFile={d / 'slurmd.log'}
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
SwitchType=switch/none
MpiDefault=none
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
ReturnToService=2
KillWait=5
MinJobAge=300
SlurmctldTimeout=30
SlurmdTimeout=30
InactiveLimit=0
NodeName={host} CPUs={cpus} RealMemory={mem_mb} State=UNKNOWN
PartitionName=debug Nodes={host} Default=YES MaxTime=INFINITE State=UP OverSubscribe=NO
"""


def start(d: Path, timeout: float = 60.0) -> Path:
    """Start the cluster in `d`; returns its slurm.conf."""
    why = missing()
    if why:
        raise SystemExit(f"slurm_cluster: {why}")
    d = d.resolve()
    for sub in ("state", "spool", "munge"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    os.chmod(d / "munge", 0o700)
    key = d / "munge" / "munge.key"
    if not key.is_file():
        key.write_bytes(os.urandom(1024))
        os.chmod(key, 0o400)
    host = socket.gethostname().split(".")[0]
    mem = int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 ** 20 * 0.9)
    conf = d / "slurm.conf"
    conf.write_text(conf_text(d, host, os.cpu_count() or 1, mem, _free_port(), _free_port()))
    env = {**os.environ, "SLURM_CONF": str(conf)}
    subprocess.run([_tool("munged"), "--force", f"--key-file={key}", f"--socket={d / 'munge' / 'munge.socket'}",
                    f"--pid-file={d / 'munge' / 'munged.pid'}", f"--log-file={d / 'munge' / 'munged.log'}",
                    f"--seed-file={d / 'munge' / 'munged.seed'}"], check=True, env=env)
    subprocess.run([_tool("slurmctld"), "-i"], check=True, env=env)  # -i: ignore state left by a crash
    subprocess.run([_tool("slurmd")], check=True, env=env)
    t0 = time.time()
    while time.time() - t0 < timeout:
        r = subprocess.run([_tool("sinfo"), "-h", "-o", "%t"], capture_output=True, text=True, env=env)
        if r.returncode == 0 and r.stdout.strip() in ("idle", "mix", "alloc"):
            return conf
        time.sleep(0.5)
    stop(d)
    raise SystemExit(f"slurm_cluster: the node did not come up in {timeout:.0f} s (logs: {d}/*.log)")


def stop(d: Path) -> None:
    """Cancel every job of the cluster (their processes go with them), then stop the daemons
    started in `d` (each by its pid file), waiting for them to go."""
    d = d.resolve()
    env = {**os.environ, "SLURM_CONF": str(d / "slurm.conf")}
    if (d / "slurm.conf").is_file():
        subprocess.run([_tool("scancel"), "--full", "--user", str(os.getuid())], env=env, capture_output=True)
        for _ in range(60):
            r = subprocess.run([_tool("squeue"), "-h"], env=env, capture_output=True, text=True)
            if r.returncode != 0 or not r.stdout.strip():
                break
            time.sleep(0.5)
    for name, pid_file in (("slurmd", d / "slurmd.pid"), ("slurmctld", d / "slurmctld.pid"),
                           ("munged", d / "munge" / "munged.pid")):
        try:
            pid = int(pid_file.read_text().strip())
        except (OSError, ValueError):
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
        else:
            os.kill(pid, signal.SIGKILL)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("action", choices=("start", "stop"))
    ap.add_argument("dir", type=Path)
    a = ap.parse_args(argv)
    if a.action == "start":
        conf = start(a.dir)
        print(f"export SLURM_CONF={conf}")
    else:
        stop(a.dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
