#!/usr/bin/env python3
"""Start and stop a throw-away single-node SLURM cluster on this machine.

Used by ``tests/workflow/test_slurm.py`` (through the ``slurm_cluster`` fixture in
``tests/slurm_fixtures.py``) and runnable by hand to try the SLURM profile locally::

    sudo bash scripts/install_slurm.sh        # once: slurmctld, slurmd, slurm-client, munge
    sudo python scripts/local_slurm.py start  # writes /etc/slurm/slurm.conf, starts daemons
    python scripts/local_slurm.py status      # sinfo / squeue
    snakemake --profile workflow/profiles/slurm ...
    sudo python scripts/local_slurm.py stop   # stops exactly those daemons, restores config

Needs root. What ``start`` does:

* writes ``/etc/slurm/slurm.conf`` (an existing one is moved aside to
  ``slurm.conf.vprflow-backup`` and put back by ``stop``). The file must live at the
  default path: each Snakemake job runs under ``srun``, which strips every ``SLURM_*``
  variable (``SLURM_CONF`` included) from the job step's environment.
* creates the munge key if it is missing and starts ``munged`` (as user ``munge``)
  unless a munged already answers on the default socket (then that one is used and
  left alone);
* starts ``slurmctld -D`` and ``slurmd -D`` as child processes (foreground mode,
  explicit pid files), records their PIDs and waits until ``sinfo`` shows the node
  ``idle``.

All state (StateSaveLocation, SlurmdSpoolDir, daemon logs, pid files and
``cluster.json``, the record ``stop`` reads) lives under one work directory,
``/tmp/vprflow-slurm`` by default.

The cluster: one node named after ``hostname -s`` (address 127.0.0.1), CPUs = nproc,
RealMemory a little below the machine's memory, one partition ``debug`` (default),
no accounting (``sacct`` answers "accounting storage is disabled", so the Snakemake
profile sets ``slurm-status-command: squeue``), ``ProctrackType=proctrack/linuxproc``,
``TaskPlugin=task/none``, ``SelectType=select/cons_tres`` with ``CR_Core_Memory``,
no GPUs (no GRES).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SLURM_CONF = Path("/etc/slurm/slurm.conf")
CGROUP_CONF = Path("/etc/slurm/cgroup.conf")
BACKUP_SUFFIX = ".vprflow-backup"
MARKER = "# Written by vprflow scripts/local_slurm.py -- restored/removed by 'local_slurm.py stop'"
MUNGE_KEY = Path("/etc/munge/munge.key")
MUNGE_SOCKET_DIR = Path("/run/munge")
DEFAULT_WORKDIR = Path("/tmp/vprflow-slurm")
PARTITION = "debug"
STATE_FILE = "cluster.json"
# Unix sockets (slurmd's spool holds one per job step) must have paths < 108 bytes.
MAX_SPOOL_PATH = 60
# The SLURM executor plugin only trusts `squeue` if finished jobs stay visible for at
# least 3 x its first status-check delay (default 40 s): keep them for 10 minutes.
MIN_JOB_AGE = 600


class ClusterError(RuntimeError):
    """A daemon did not start (the message includes its log) or the node never got idle."""


@dataclasses.dataclass
class Daemon:
    name: str
    pid: int
    starttime: int  # field 22 of /proc/<pid>/stat, to recognise the process later
    log: str
    cmd: list[str]


@dataclasses.dataclass
class ClusterHandle:
    workdir: Path
    node: str
    cpus: int
    real_memory_mb: int
    partition: str
    conf_path: Path
    conf_backup: Path | None  # where a pre-existing slurm.conf was moved to
    cgroup_backup: Path | None
    wrote_cgroup_conf: bool
    created_munge_key: bool
    daemons: list[Daemon]
    # Popen objects of daemons started by this process (not persisted), so that
    # stop_cluster() can reap them; a handle loaded from cluster.json has none.
    _procs: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def pids(self) -> dict[str, int]:
        return {d.name: d.pid for d in self.daemons}

    def to_json(self) -> dict:
        return {
            "workdir": str(self.workdir),
            "node": self.node,
            "cpus": self.cpus,
            "real_memory_mb": self.real_memory_mb,
            "partition": self.partition,
            "conf_path": str(self.conf_path),
            "conf_backup": str(self.conf_backup) if self.conf_backup else None,
            "cgroup_backup": str(self.cgroup_backup) if self.cgroup_backup else None,
            "wrote_cgroup_conf": self.wrote_cgroup_conf,
            "created_munge_key": self.created_munge_key,
            "daemons": [dataclasses.asdict(d) for d in self.daemons],
        }

    @classmethod
    def from_json(cls, data: dict) -> ClusterHandle:
        return cls(
            workdir=Path(data["workdir"]),
            node=data["node"],
            cpus=data["cpus"],
            real_memory_mb=data["real_memory_mb"],
            partition=data["partition"],
            conf_path=Path(data["conf_path"]),
            conf_backup=Path(data["conf_backup"]) if data["conf_backup"] else None,
            cgroup_backup=Path(data["cgroup_backup"]) if data["cgroup_backup"] else None,
            wrote_cgroup_conf=data["wrote_cgroup_conf"],
            created_munge_key=data["created_munge_key"],
            daemons=[Daemon(**d) for d in data["daemons"]],
        )

    def save(self) -> None:
        path = self.workdir / STATE_FILE
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=2) + "\n")
        os.replace(tmp, path)


# --------------------------------------------------------------------------- helpers


def _log(msg: str) -> None:
    print(f"local_slurm: {msg}", file=sys.stderr, flush=True)


def _which(name: str) -> str | None:
    return shutil.which(name) or next(
        (str(p) for p in (Path("/usr/sbin") / name, Path("/sbin") / name) if p.exists()), None
    )


def missing_tools() -> list[str]:
    """Names of the SLURM/munge programs this script needs that are not installed."""
    tools = ["slurmctld", "slurmd", "munged", "sinfo", "squeue", "sbatch", "srun", "scontrol"]
    return [t for t in tools if _which(t) is None]


def _short_hostname() -> str:
    out = subprocess.run(["hostname", "-s"], capture_output=True, text=True, check=False)
    name = out.stdout.strip() or socket.gethostname().split(".")[0]
    return name


def _mem_total_mb() -> int:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) // 1024
    raise ClusterError("cannot read MemTotal from /proc/meminfo")


def _real_memory_mb(total_mb: int) -> int:
    # slurmd marks a node invalid when RealMemory exceeds what it detects: stay 5 %
    # (at least 256 MB) below the machine's memory.
    return max(256, total_mb - max(256, total_mb // 20))


def _proc_starttime(pid: int) -> int | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # the command name (field 2) may contain spaces: split after its closing ")"
    fields = stat[stat.rindex(")") + 2 :].split()
    if fields[0] == "Z":  # zombie: already dead
        return None
    return int(fields[19])


def _is_our_process(d: Daemon) -> bool:
    return _proc_starttime(d.pid) == d.starttime


def _tail(path: Path | str, n: int = 40) -> str:
    try:
        lines = Path(path).read_text(errors="replace").splitlines()
    except OSError as exc:
        return f"    (no log: {exc})"
    if not lines:
        return "    (log is empty)"
    return "\n".join("    " + line for line in lines[-n:])


def _munge_works() -> bool:
    """True if a munged answers on the default socket."""
    try:
        enc = subprocess.run(["munge", "-n"], capture_output=True, timeout=10, check=False)
        if enc.returncode != 0:
            return False
        dec = subprocess.run(
            ["unmunge"], input=enc.stdout, capture_output=True, timeout=10, check=False
        )
        return dec.returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def _run_quiet(cmd: list[str], timeout: float = 15) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SLURM_")}
    try:
        return subprocess.run(
            cmd, capture_output=True, text=True, timeout=timeout, check=False, env=env
        )
    except subprocess.TimeoutExpired as exc:
        return subprocess.CompletedProcess(cmd, 124, "", f"timed out: {exc}")


def node_state(node: str) -> str | None:
    """The node's state as sinfo prints it (``idle``, ``mix``, ``down*`` ...), or None."""
    out = _run_quiet(["sinfo", "-h", "-N", "-n", node, "-o", "%t"])
    if out.returncode != 0 or not out.stdout.strip():
        return None
    return out.stdout.split()[0]


# --------------------------------------------------------------------------- config


def render_slurm_conf(
    workdir: Path, spooldir: Path, node: str, cpus: int, real_memory_mb: int
) -> str:
    return f"""{MARKER}
# Single-node test cluster for vprflow; state and logs under {workdir}
ClusterName=vprflow-local
SlurmctldHost={node}(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
MpiDefault=none
MailProg=/bin/true
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
SlurmdParameters=config_overrides
MinJobAge={MIN_JOB_AGE}
KillWait=5
InactiveLimit=0
Waittime=0
SlurmctldTimeout=30
SlurmdTimeout=60
StateSaveLocation={workdir / "state"}
SlurmdSpoolDir={spooldir}
SlurmctldPidFile={workdir / "slurmctld.pid"}
SlurmdPidFile={workdir / "slurmd.pid"}
SlurmctldLogFile={workdir / "slurmctld.log"}
SlurmdLogFile={workdir / "slurmd.log"}
SlurmctldDebug=info
SlurmdDebug=info
NodeName={node} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={real_memory_mb} State=UNKNOWN
PartitionName={PARTITION} Nodes={node} Default=YES MaxTime=INFINITE State=UP
"""


def _install_file(path: Path, text: str) -> Path | None:
    """Write ``text`` to ``path``; move a foreign pre-existing file to ``<path>.vprflow-backup``.

    Returns the backup path (None when there was nothing to keep). A file carrying our
    MARKER is a leftover of an earlier run that was not stopped: it is overwritten, and
    an older backup (if any) is kept for ``stop`` to restore.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    backup = path.with_name(path.name + BACKUP_SUFFIX)
    if path.exists() and MARKER not in path.read_text(errors="replace"):
        if backup.exists():
            raise ClusterError(
                f"{path} exists and so does {backup}: refusing to overwrite a backup; "
                "sort them out by hand"
            )
        os.replace(path, backup)
    tmp = path.with_name(path.name + ".vprflow-tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return backup if backup.exists() else None


def _restore_file(path: Path, backup: Path | None) -> None:
    if path.exists() and MARKER in path.read_text(errors="replace"):
        path.unlink()
    if backup is not None and backup.exists():
        os.replace(backup, path)


# --------------------------------------------------------------------------- daemons


def _spawn(
    name: str, cmd: list[str], log: Path, workdir: Path | str, user: str | None = None
) -> tuple[Daemon, subprocess.Popen]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SLURM_")}
    with open(log, "ab") as out:
        proc = subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            cwd=workdir,
            env=env,
            start_new_session=True,  # survives the CLI's exit and Ctrl-C in a test run
            user=user,
            group=user,
            extra_groups=[] if user else None,
        )
    starttime = None
    for _ in range(50):
        starttime = _proc_starttime(proc.pid)
        if starttime is not None or proc.poll() is not None:
            break
        time.sleep(0.02)
    return Daemon(name, proc.pid, starttime or -1, str(log), cmd), proc


def _daemon_error(handle: ClusterHandle, what: str) -> ClusterError:
    parts = [what]
    for d in handle.daemons:
        proc = handle._procs.get(d.name)
        rc = proc.poll() if proc is not None else None
        status = f"exited with code {rc}" if rc is not None else f"pid {d.pid}"
        # The daemon's stdout/stderr holds everything, including errors from before it
        # opened its own log file; fall back to that log file if stdout stayed empty.
        log = Path(d.log)
        own_log = handle.workdir / f"{d.name}.log"
        if (not log.exists() or log.stat().st_size == 0) and own_log.exists():
            log = own_log
        parts.append(f"--- {d.name} ({status}); tail of {log}:\n{_tail(log)}")
    return ClusterError("\n".join(parts))


def _wait_alive(handle: ClusterHandle, name: str, seconds: float) -> None:
    """Fail fast if the daemon just started exits within ``seconds``."""
    proc = handle._procs[name]
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise _daemon_error(handle, f"{name} exited right after start (code {proc.returncode})")
        time.sleep(0.1)


def _start_munged(handle: ClusterHandle) -> None:
    if _munge_works():
        _log("a munged already answers on the default socket: using it (it will not be stopped)")
        return
    munged = _which("munged")
    try:
        munge_user = pwd.getpwnam("munge")
    except KeyError as exc:
        raise ClusterError("user 'munge' does not exist: install the munge package") from exc
    if not MUNGE_KEY.exists():
        _log(f"creating munge key {MUNGE_KEY}")
        MUNGE_KEY.parent.mkdir(parents=True, exist_ok=True)
        os.chown(MUNGE_KEY.parent, munge_user.pw_uid, munge_user.pw_gid)
        subprocess.run(
            [_which("mungekey") or "mungekey", "--create", f"--keyfile={MUNGE_KEY}"], check=True
        )
        os.chown(MUNGE_KEY, munge_user.pw_uid, munge_user.pw_gid)
        os.chmod(MUNGE_KEY, 0o600)
        handle.created_munge_key = True
    # munged refuses a key not owned by the user it runs as; it runs as 'munge'.
    MUNGE_SOCKET_DIR.mkdir(parents=True, exist_ok=True)
    os.chown(MUNGE_SOCKET_DIR, munge_user.pw_uid, munge_user.pw_gid)
    os.chmod(MUNGE_SOCKET_DIR, 0o755)
    # Seed and pid files stay at munge's defaults (/var/lib/munge, /run/munge): munged
    # runs as 'munge' and insists on directories that user owns, which the work
    # directory (e.g. pytest's 0700 tmp dirs) is not. Its stderr is our log file.
    var_lib = Path("/var/lib/munge")
    var_lib.mkdir(parents=True, exist_ok=True)
    os.chown(var_lib, munge_user.pw_uid, munge_user.pw_gid)
    cmd = [munged, "--foreground"]
    daemon, proc = _spawn("munged", cmd, handle.workdir / "munged.log", "/", user="munge")
    handle.daemons.append(daemon)
    handle._procs["munged"] = proc
    handle.save()
    deadline = time.monotonic() + 15
    while not _munge_works():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise _daemon_error(handle, "munged did not start")
        time.sleep(0.2)


def _start_slurm_daemon(handle: ClusterHandle, name: str) -> None:
    exe = _which(name)
    if exe is None:
        raise ClusterError(f"{name} is not installed: run scripts/install_slurm.sh")
    # -D: stay in the foreground (we own the process); -i: ignore unreadable old state
    cmd = [exe, "-D", "-i"] if name == "slurmctld" else [exe, "-D"]
    daemon, proc = _spawn(name, cmd, handle.workdir / f"{name}.stdout.log", handle.workdir)
    handle.daemons.append(daemon)
    handle._procs[name] = proc
    handle.save()
    _wait_alive(handle, name, 1.0)


def _wait_controller(handle: ClusterHandle, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if handle._procs["slurmctld"].poll() is not None:
            raise _daemon_error(handle, "slurmctld exited")
        if _run_quiet(["scontrol", "ping"], timeout=5).stdout.count("UP"):
            return
        time.sleep(0.3)
    raise _daemon_error(handle, f"slurmctld did not answer 'scontrol ping' within {timeout:.0f} s")


def _wait_idle(handle: ClusterHandle, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    state = None
    while time.monotonic() < deadline:
        for name in ("slurmctld", "slurmd"):
            if handle._procs[name].poll() is not None:
                raise _daemon_error(handle, f"{name} exited while waiting for the node")
        state = node_state(handle.node)
        if state == "idle":
            return
        if state in {"down", "down*", "drain", "drain*", "inval", "inval*"}:
            # a node that registered with a bad config: try to resume it once
            _run_quiet(["scontrol", "update", f"NodeName={handle.node}", "State=RESUME"])
        time.sleep(0.5)
    reason = _run_quiet(["sinfo", "-h", "-N", "-o", "%N %t %E"]).stdout.strip()
    raise _daemon_error(
        handle,
        f"node {handle.node} not idle after {timeout:.0f} s (last state: {state}; sinfo: {reason})",
    )


# --------------------------------------------------------------------------- API


def start_cluster(workdir: Path | str = DEFAULT_WORKDIR, timeout: float = 60.0) -> ClusterHandle:
    """Start munged (if needed), slurmctld and slurmd; return once the node is idle.

    On failure everything started so far is stopped again, the config restored, and a
    ClusterError carrying the daemons' log tails is raised.
    """
    if os.geteuid() != 0:
        raise ClusterError("starting a SLURM cluster needs root")
    missing = missing_tools()
    if missing:
        raise ClusterError(
            f"not installed: {', '.join(missing)}; run: sudo bash scripts/install_slurm.sh"
        )
    workdir = Path(workdir).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    state_file = workdir / STATE_FILE
    if state_file.exists():
        old = ClusterHandle.from_json(json.loads(state_file.read_text()))
        if any(_is_our_process(d) for d in old.daemons):
            raise ClusterError(
                f"a cluster from {workdir} is still running ({old.pids}): "
                f"run 'python scripts/local_slurm.py stop --workdir {workdir}' first"
            )
        stop_cluster(old)  # restore whatever a crashed run left behind
    if SLURM_CONF.exists() and "UP" in _run_quiet(["scontrol", "ping"], timeout=10).stdout:
        hint = "stop it first"
        text = SLURM_CONF.read_text(errors="replace")
        if MARKER in text and "state and logs under " in text:
            other = text.split("state and logs under ", 1)[1].splitlines()[0].strip()
            hint = f"stop it first: python scripts/local_slurm.py stop --workdir {other}"
        raise ClusterError(f"a SLURM controller already answers for {SLURM_CONF}: {hint}")
    (workdir / "state").mkdir(exist_ok=True)
    spooldir = workdir / "spool"
    if len(str(spooldir)) > MAX_SPOOL_PATH:
        spooldir = Path(tempfile.mkdtemp(prefix="vprflow-slurmd-", dir="/tmp"))
    spooldir.mkdir(exist_ok=True)
    for log in ("slurmctld.log", "slurmd.log"):
        (workdir / log).unlink(missing_ok=True)

    node = _short_hostname()
    cpus = os.cpu_count() or 1
    real_memory = _real_memory_mb(_mem_total_mb())
    handle = ClusterHandle(
        workdir=workdir,
        node=node,
        cpus=cpus,
        real_memory_mb=real_memory,
        partition=PARTITION,
        conf_path=SLURM_CONF,
        conf_backup=None,
        cgroup_backup=None,
        wrote_cgroup_conf=False,
        created_munge_key=False,
        daemons=[],
    )
    try:
        handle.conf_backup = _install_file(
            SLURM_CONF, render_slurm_conf(workdir, spooldir, node, cpus, real_memory)
        )
        handle.save()
        _start_munged(handle)
        _start_slurm_daemon(handle, "slurmctld")
        _wait_controller(handle, timeout)
        _start_slurm_daemon(handle, "slurmd")
        _wait_idle(handle, timeout)
    except BaseException:
        try:
            stop_cluster(handle)
        except Exception as exc:  # noqa: BLE001 - keep the original error
            _log(f"cleanup after failed start also failed: {exc}")
        raise
    _log(f"cluster up: node {node} ({cpus} CPUs, {real_memory} MB), pids {handle.pids}")
    return handle


def _terminate(d: Daemon, proc: subprocess.Popen | None, grace: float = 15.0) -> None:
    if proc is not None:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(grace)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        return
    if not _is_our_process(d):
        return  # gone already, or the PID now belongs to someone else
    os.kill(d.pid, signal.SIGTERM)
    deadline = time.monotonic() + grace
    while time.monotonic() < deadline:
        if not _is_our_process(d):
            return
        time.sleep(0.1)
    if _is_our_process(d):
        os.kill(d.pid, signal.SIGKILL)


def stop_cluster(handle: ClusterHandle) -> None:
    """Cancel the cluster's jobs, stop exactly the daemons start_cluster() started and
    restore the config files."""
    errors = []
    by_name = {d.name: d for d in handle.daemons}
    ctld = by_name.get("slurmctld")
    if ctld is not None and (
        _is_our_process(ctld)
        and (handle._procs.get("slurmctld") is None or handle._procs["slurmctld"].poll() is None)
    ):
        # Jobs (their slurmstepd processes) belong to this throw-away cluster: end them.
        _run_quiet(["scancel", "--full", f"--partition={handle.partition}"], timeout=10)
    for name in ("slurmd", "slurmctld", "munged"):
        d = by_name.get(name)
        if d is None:
            continue
        try:
            _terminate(d, handle._procs.get(name))
        except OSError as exc:
            errors.append(f"{name} (pid {d.pid}): {exc}")
    for name in ("slurmctld", "slurmd"):
        pidfile = handle.workdir / f"{name}.pid"
        pidfile.unlink(missing_ok=True)
    _restore_file(handle.conf_path, handle.conf_backup)
    if handle.wrote_cgroup_conf:
        _restore_file(CGROUP_CONF, handle.cgroup_backup)
    (handle.workdir / STATE_FILE).unlink(missing_ok=True)
    if errors:
        raise ClusterError("could not stop: " + "; ".join(errors))


def load_handle(workdir: Path | str = DEFAULT_WORKDIR) -> ClusterHandle | None:
    path = Path(workdir).resolve() / STATE_FILE
    if not path.exists():
        return None
    return ClusterHandle.from_json(json.loads(path.read_text()))


# --------------------------------------------------------------------------- CLI


def _status(workdir: Path) -> int:
    handle = load_handle(workdir)
    if handle is None:
        print(f"no cluster recorded in {workdir}")
    else:
        for d in handle.daemons:
            alive = "running" if _is_our_process(d) else "NOT running"
            print(f"{d.name:10s} pid {d.pid:<8d} {alive}   log {d.log}")
    if not SLURM_CONF.exists():
        print(f"{SLURM_CONF} does not exist: no cluster configured")
        return 1
    for cmd in (["sinfo"], ["squeue", "--states=all"]):
        out = _run_quiet(cmd)
        print(f"$ {' '.join(cmd)}\n{(out.stdout + out.stderr).rstrip()}")
    return 0 if handle is not None and node_state(handle.node) is not None else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=["start", "stop", "status"])
    parser.add_argument(
        "--workdir",
        default=str(DEFAULT_WORKDIR),
        help=f"state, spool and log directory (default {DEFAULT_WORKDIR})",
    )
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for idle")
    args = parser.parse_args(argv)
    workdir = Path(args.workdir).resolve()
    try:
        if args.action == "start":
            handle = start_cluster(workdir, timeout=args.timeout)
            print(json.dumps(handle.pids))
            print(f"stop with: python {sys.argv[0]} stop --workdir {workdir}")
            return 0
        if args.action == "stop":
            handle = load_handle(workdir)
            if handle is None:
                print(f"no cluster recorded in {workdir}: nothing to stop")
                return 0
            stop_cluster(handle)
            print(f"stopped {handle.pids}; config restored")
            return 0
        return _status(workdir)
    except ClusterError as exc:
        print(f"local_slurm: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
