"""Joining a cluster of processes (``jax.distributed``) and agreeing across them.

A sweep or a batched fit run on several processes (several hosts, or several processes on one
host) is the same program started once per process: every process calls :func:`join` before
any JAX computation, then runs the same calls with the same inputs. ``jax.devices()`` then
lists the devices of every process, :func:`tuning.shard.sharded_map` splits the batch over all
of them and hands every process the whole result, and only process 0 writes files
(:func:`is_writer`).

:func:`join` takes an explicit coordinator (``HOST:PORT`` of process 0, the number of
processes and this process's index), or, given none, detects a cluster launcher that JAX
knows (SLURM's ``srun`` with more than one task, Open MPI's ``mpirun`` with more than one
rank) and lets ``jax.distributed.initialize()`` read the rest from the environment.

Once joined, every process checks that all were started alike: the same number of local
devices, and (explicit coordinator) the same number of processes and coordinator; otherwise
each stops with the same ``ValueError`` naming what differs. A process that stops (killed,
crashed) or stays silent for :func:`heartbeat_seconds` (``min(timeout_s, 10)`` s) stops every
other process: each writes one line on standard error saying so and exits with status 2
(when process 0, the coordinator, stops, JAX itself aborts the others at once). A process
that ends on an error (an uncaught exception, or a ``diffpen`` command's non-zero exit status:
:func:`mark_failed`) stops the others within about 3 s, naming it, instead of leaving them
waiting in a collective for it.
"""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import sys
import time
from typing import Callable

import numpy as np

__all__ = ["join", "check", "detect", "parse_coordinator", "is_writer", "process_count",
           "from_process_zero", "check_same", "check_local_devices", "jaxpr_digest",
           "heartbeat_seconds", "mark_failed", "lost_process"]

# seconds a process may stay silent before the others take it for stopped (at most timeout_s)
HEARTBEAT_S = 10
# exit status of a process stopped because another process of the cluster stopped
STOPPED_STATUS = 2


def parse_coordinator(text: str) -> tuple[str, int]:
    """``"HOST:PORT"`` -> (host, port); a clear ``ValueError`` otherwise."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"coordinator must be HOST:PORT (the address of process 0, e.g. "
                         f"node001:12345), got {text!r}.")
    return host, int(port)


def _int_env(name: str) -> int:
    try:
        return int(os.environ.get(name, "1"))
    except ValueError:
        return 1


def detect() -> str | None:
    """The cluster launcher this process was started by, if it started more than one process
    and JAX can read its environment: ``"slurm"`` (``srun``, ``SLURM_NTASKS`` > 1),
    ``"ompi"`` (Open MPI's ``mpirun``, ``OMPI_COMM_WORLD_SIZE`` > 1), else None."""
    slurm = ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_NTASKS", "SLURM_PROCID",
             "SLURM_LOCALID")
    if all(v in os.environ for v in slurm) and _int_env("SLURM_NTASKS") > 1:
        return "slurm"
    if "OMPI_MCA_orte_hnp_uri" in os.environ and _int_env("OMPI_COMM_WORLD_SIZE") > 1:
        return "ompi"
    return None


def check(coordinator: str | None, num_processes: int | None,
          process_id: int | None) -> bool:
    """Check a cluster description before anything runs: all three given (True) or none
    (False); a clear ``ValueError`` otherwise."""
    given = [coordinator is not None, num_processes is not None, process_id is not None]
    if any(given) and not all(given):
        raise ValueError("joining a cluster needs all three of the coordinator (HOST:PORT, "
                         "the same for every process), the number of processes and this "
                         f"process's id; got coordinator={coordinator!r}, "
                         f"num_processes={num_processes!r}, process_id={process_id!r}.")
    if not all(given):
        return False
    parse_coordinator(coordinator)
    if isinstance(num_processes, bool) or int(num_processes) != num_processes \
            or num_processes < 1:
        raise ValueError(f"the number of processes must be an integer >= 1, got "
                         f"{num_processes!r}.")
    if isinstance(process_id, bool) or int(process_id) != process_id \
            or not 0 <= process_id < num_processes:
        raise ValueError(f"the process id must be an integer in [0, {num_processes - 1}], "
                         f"got {process_id!r}.")
    return True


def join(coordinator: str | None = None, num_processes: int | None = None,
         process_id: int | None = None, *, timeout_s: int = 300) -> bool:
    """Join the cluster (``jax.distributed.initialize``); call before any JAX computation.

    Args:
      coordinator: ``"HOST:PORT"`` where process 0 listens (every process gives the same);
        None: detect a launcher (:func:`detect`), or stay a single process.
      num_processes: processes in all (>= 1), with ``coordinator``.
      process_id: this process's index, ``0 <= process_id < num_processes``.
      timeout_s: seconds to wait for every process to join before failing (no hang).
    Returns: True when this process is part of a cluster (now or already), False when it runs
      alone. Raises ``ValueError`` for an incomplete or inconsistent set of arguments.

    Before it waits, it writes one line on standard error: which process waits, for how long
    and on which coordinator (a process that is never joined by the others, e.g. because
    process 0 stopped or was given another number of processes, says why it is waiting).

    Once joined, it raises the same ``ValueError`` on every process when the processes have
    different numbers of local devices, or were given different ``num_processes`` or
    ``coordinator``. Afterwards, a process that stops (killed, crashed) or stays silent for
    :func:`heartbeat_seconds` (``min(timeout_s, 10)`` s) makes every other process write one
    line on standard error and exit with status 2; at the end, a finishing process waits up to
    ``max(timeout_s, 300)`` s for the others to finish too.
    """
    import jax
    given = check(coordinator, num_processes, process_id)
    if isinstance(timeout_s, bool) or not isinstance(timeout_s, (int, float)) \
            or not timeout_s >= 1:
        raise ValueError(f"timeout_s must be a number of seconds >= 1, got {timeout_s!r}.")
    if jax.distributed.is_initialized():
        return True
    if given:
        if num_processes == 1:
            return False
        if int(process_id) == 0:
            _check_port_free(coordinator)
        _say_waiting(f"process {int(process_id)} of {int(num_processes)}", timeout_s,
                     f"the coordinator {coordinator} (every process needs the same coordinator "
                     f"and number of processes, and its own id in 0..{int(num_processes) - 1})")
        _initialize(timeout_s, coordinator, int(num_processes), int(process_id))
        _check_joined(timeout_s, coordinator, int(num_processes))
        return True
    launcher = detect()
    if launcher is None:
        return False
    name = {"slurm": "SLURM", "ompi": "Open MPI"}.get(launcher, launcher)
    _say_waiting("this process", timeout_s, f"the coordinator that the {name} launch names")
    _initialize(timeout_s)
    _check_joined(timeout_s)
    return True


def _check_port_free(coordinator: str) -> None:
    """Process 0 hosts the coordinator on its port: refuse, with a ``ValueError`` that says
    what to change, a port another program already listens on (e.g. a second process given
    ``process_id=0``), before JAX starts its coordination service. (Two processes 0 made both
    abort inside JAX with a C++ stack trace and no word of the cause.) A port in TIME_WAIT
    from a run that just ended is free (``SO_REUSEADDR``, as JAX's server binds); any other
    failure to bind the probe (no IPv4, a privileged port) is left to JAX's own bind."""
    import errno
    import socket
    port = parse_coordinator(coordinator)[1]
    try:
        probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    except OSError:             # no IPv4 here: nothing to check with; JAX binds as it can
        return
    try:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind(("", port))
    except OSError as exc:
        if exc.errno != errno.EADDRINUSE:   # not a port in use: JAX's own bind says why
            return
        raise ValueError(
            f"process 0 hosts the coordinator on port {port}, but that port is in use "
            f"({exc.strerror}): another process was given process id 0 too (give each "
            "process its own id, 0 on the coordinator's host only), or another program "
            "listens there (choose another port in --coordinator).") from None
    finally:
        probe.close()


def heartbeat_seconds(timeout_s) -> int:
    """Seconds a process of a cluster may stay silent before the others take it for stopped:
    ``min(timeout_s, HEARTBEAT_S)`` (10 s by default), at least 2."""
    return max(2, min(int(timeout_s), HEARTBEAT_S))


def _initialize(timeout_s, *args) -> None:
    """``jax.distributed.initialize(*args)`` waiting ``timeout_s`` s for the others, then the
    watch of :func:`_watch_cluster`. JAX's own heartbeat check is set to twice
    :func:`heartbeat_seconds` (JAX's default is 100 s: the survivors of a killed process
    hung that long), so that it only backs up the watch. A finishing process waits up to
    ``max(timeout_s, 300)`` s for the others to finish too (JAX aborts every process when that
    wait runs out, so it must cover process 0 writing its files after the others ended)."""
    import jax
    silent = heartbeat_seconds(timeout_s)
    jax.distributed.initialize(*args, initialization_timeout=int(timeout_s),
                               heartbeat_timeout_seconds=2 * silent,
                               shutdown_timeout_seconds=max(int(timeout_s), 300))
    _keep_signal_handlers()
    _watch_cluster(silent)


def _keep_signal_handlers() -> None:
    """Install again the Python handlers of SIGTERM and SIGINT that were set before joining:
    ``jax.distributed.initialize`` puts its preemption notifier on SIGTERM, which replaced
    a ``diffpen`` command's handler (a cluster sweep sent SIGTERM, as SLURM does at its time
    limit, logged "SIGTERM caught" and ran on to the end). Default handlers are left to JAX.
    Only from the main thread (where handlers are set)."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGTERM, signal.SIGINT):
        handler = signal.getsignal(sig)
        if callable(handler) and handler is not signal.default_int_handler:
            signal.signal(sig, handler)


_WATCH_KEY = "diffpen/alive/"
_WATCH_PERIOD_S = 1.0
# seconds a process that sees another end on an error waits before stopping (the others
# usually raise the same error themselves at the same moment, and say so first)
_FAILED_GRACE_S = 2.0
_failure: list = []            # why this process is ending on an error (mark_failed)
_watching: list = []           # True once this process watches a cluster it joined


def mark_failed(why: str, status: int = 1) -> None:
    """Say that this process is ending on an error (called by the ``diffpen`` commands on a
    non-zero exit status; an uncaught exception does it by itself once joined). When it
    ends, every other process of the cluster stops within about 3 s with a line naming it,
    instead of waiting in a collective for it until JAX's shutdown wait (300 s) runs out; and
    this process exits at once with ``status`` instead of waiting in that shutdown itself
    (where the others stopping would abort it). Does nothing outside a cluster."""
    if _watching and not _failure:
        _failure.append((" ".join(str(why).split())[:200], int(status)))


def _watch_cluster(silent_s: int) -> None:
    """Watch the other processes from a background thread, so that a process that stops
    (killed, crashed, frozen) stops the others promptly and clearly.

    Every second each process writes a counter in the cluster's key-value store and reads the
    others'. A process whose counter has not moved for ``silent_s`` s, or a coordinator
    (process 0) that cannot be reached for ``silent_s`` s, makes this process write one line
    on standard error and exit with status 2 (:data:`STOPPED_STATUS`) at once: the others can
    no longer answer a collective, and JAX would otherwise abort it (SIGABRT) only after its
    heartbeat time (even when this process has already ended and waits in JAX's shutdown for
    the others). A process that ends says so first (``atexit``), so that the others do not
    take it for stopped while they finish."""
    import atexit
    import threading

    import jax
    from jax._src import distributed as jax_distributed
    client = jax_distributed.global_state.client
    me, n = jax.process_index(), jax.process_count()
    ended = threading.Event()       # this process ended (atexit): no more counting
    lock = threading.Lock()

    def watch() -> None:
        count, failing = 0, None
        start = time.monotonic()
        seen = {i: (None, start) for i in range(n) if i != me}    # counter, when it moved
        failed_at: dict = {}                                       # process -> when seen
        while True:
            time.sleep(_WATCH_PERIOD_S)
            if jax_distributed.global_state.client is not client:
                return                            # JAX shut the cluster down
            count += 1
            try:
                with lock:
                    if not ended.is_set():
                        client.key_value_set(f"{_WATCH_KEY}{me}", str(count),
                                             allow_overwrite=True)
                values = dict(client.key_value_dir_get(_WATCH_KEY))
                failing = None
            except Exception as exc:              # the coordinator is gone or unreachable
                if jax_distributed.global_state.client is not client:
                    return
                failing = time.monotonic() if failing is None else failing
                if time.monotonic() - failing >= silent_s:
                    line = (str(exc).strip().splitlines() or [""])[0][:200]
                    _stop(me, f"the coordinator (process 0) has not answered for {silent_s} s "
                              f"({line})")
                continue
            now = time.monotonic()
            for i in list(seen):
                value = values.get(f"{_WATCH_KEY}{i}")
                if value == "exit":               # ended normally: no longer watched
                    del seen[i]
                elif value is not None and value.startswith("failed"):
                    failed_at.setdefault(i, now)  # ended on an error: it will not answer
                    if now - failed_at[i] >= _FAILED_GRACE_S:
                        why = value[len("failed:"):] or "see its standard error"
                        # a Ctrl-C or SIGTERM is no error of the run (diffpen ... interrupted)
                        how = "ended" if why.endswith(("interrupted", "terminated")) \
                            else "ended on an error"
                        _stop(me, f"process {i} of {n} {how} ({why})")
                elif value != seen[i][0]:
                    seen[i] = (value, now)
                elif now - seen[i][1] >= silent_s:
                    _stop(me, f"process {i} of {n} has not answered for {silent_s} s (it "
                              f"was killed, crashed or froze)")

    def at_exit() -> None:
        """Runs before JAX's shutdown (``atexit``: last in, first out), which waits for every
        process: the others stop watching this one, and this one goes on watching them (a
        process that stopped would make JAX's shutdown wait, then abort)."""
        if lock.acquire(timeout=5.0):
            try:
                ended.set()
                end = f"failed:{_failure[0][0]}" if _failure else "exit"
                client.key_value_set(f"{_WATCH_KEY}{me}", end, allow_overwrite=True)
            except Exception:
                pass
            finally:
                lock.release()
        if _failure:            # ended on an error: no shutdown wait for the others
            if me == 0:
                # the coordinator leaving first would make JAX abort the others (SIGABRT)
                # before they print their own line: wait, briefly, for them to end
                _wait_for_the_others(client, me, n, _FAILED_GRACE_S + 3.0)
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(_failure[0][1])

    previous_hook = sys.excepthook

    def on_uncaught(kind, value, tb) -> None:
        """An uncaught exception ends this process on an error (runs before ``atexit``)."""
        mark_failed(f"{kind.__name__}: {value}")
        previous_hook(kind, value, tb)

    sys.excepthook = on_uncaught
    _watching.append(True)
    threading.Thread(target=watch, name="diffpen-cluster-watch", daemon=True).start()
    atexit.register(at_exit)


#: words of the errors a collective raises when another process of the cluster is gone
_LOST_PEER = ("Gloo", "Connection closed by peer", "Connection reset by peer",
              "Broken pipe")


def lost_process(error) -> str | None:
    """In a cluster, when ``error`` (an exception or its text) is a collective's failure
    because another process is gone (killed, crashed, interrupted: its connection closed;
    JAX raises it as a ``JaxRuntimeError``, or a ``ValueError`` from a jitted call), one line
    saying so, naming that process where it said why it ended; else None. The ``diffpen``
    commands print it instead of the collective's raw error (``UNKNOWN: Gloo AllGather
    failed: ... Connection closed by peer``), which says neither which process stopped nor
    what to do."""
    import jax
    text = str(error)
    if not _watching or not any(w in text for w in _LOST_PEER):
        return None
    me, n = jax.process_index(), jax.process_count()
    who = "another process is gone (killed or crashed)"
    try:
        from jax._src import distributed as jax_distributed
        values = dict(jax_distributed.global_state.client.key_value_dir_get(_WATCH_KEY))
        ended = [(i, values[f"{_WATCH_KEY}{i}"][len("failed:"):]) for i in range(n) if i != me
                 and str(values.get(f"{_WATCH_KEY}{i}", "")).startswith("failed")]
        if ended:
            who = "; ".join(f"process {i} of {n} ended ({why or 'see its standard error'})"
                            for i, why in ended)
    except Exception:               # the coordinator itself may be the one gone
        pass
    line = (text.strip().splitlines() or [""])[0][:160]
    return (f"a process of the cluster stopped: {who}, and a collective with it failed "
            f"({line}); process {me} stops too (exit status {STOPPED_STATUS}): see the "
            "standard error of the stopped process for why.")


def _wait_for_the_others(client, me: int, n: int, limit_s: float) -> None:
    """Wait up to ``limit_s`` s until every other process has said that it ended (normally
    or on an error) in the watch's key-value entries; a process stopped by the watch says
    nothing, so the wait then runs to its limit."""
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        try:
            values = dict(client.key_value_dir_get(_WATCH_KEY))
        except Exception:
            return
        if all(str(values.get(f"{_WATCH_KEY}{i}", "")).startswith(("exit", "failed"))
               for i in range(n) if i != me):
            return
        time.sleep(0.1)


#: the longest a stopping process waits for files it is writing (a sweep's .npz and .csv,
#: :func:`tuning.progress.uninterrupted`) before it exits, s
_WRITE_GRACE_S = 30.0


def _stop(me: int, why: str) -> None:
    """One line on standard error, then exit with :data:`STOPPED_STATUS` (no cleanup: the
    main thread may be waiting on the stopped process inside a collective), once files
    being written as a set are written (at most :data:`_WRITE_GRACE_S`: process 0 stopped
    between a sweep's .npz and its .csv when the others ended on SIGTERM)."""
    from .progress import held
    deadline = time.monotonic() + _WRITE_GRACE_S
    while held() and time.monotonic() < deadline:
        time.sleep(0.02)
    try:
        sys.stdout.flush()
        sys.stderr.write(f"a process of the cluster stopped: {why}; process {me} stops too "
                         f"(exit status {STOPPED_STATUS}): see the standard error of the "
                         "stopped process for why.\n")
        sys.stderr.flush()
    finally:
        os._exit(STOPPED_STATUS)


def check_local_devices() -> None:
    """Raise the same ``ValueError`` on every process unless every process of the cluster has
    the same number of local devices (the sharded programs and the collectives split every
    batch evenly over the processes). No communication: ``jax.devices()`` lists the devices
    of every process on each."""
    import jax
    counts: dict = {}
    for d in jax.devices():
        counts[d.process_index] = counts.get(d.process_index, 0) + 1
    if len(set(counts.values())) > 1:
        have = ", ".join(f"process {i} has {n}" for i, n in sorted(counts.items()))
        raise ValueError(
            f"every process of a cluster must have the same number of local devices, but "
            f"{have} ({sum(counts.values())} devices in all): give every process the same "
            f"devices (on CPU the same XLA_FLAGS=--xla_force_host_platform_device_count=N on "
            f"every process; on GPUs the same number of visible devices, e.g. "
            f"CUDA_VISIBLE_DEVICES).")


def _check_joined(timeout_s, coordinator: str | None = None,
                  num_processes: int | None = None) -> None:
    """After ``jax.distributed.initialize``: the same ``ValueError`` on every process unless
    all have the same number of local devices and were given the same number of processes
    and coordinator (a process 0 given fewer processes than the others forms a smaller
    cluster that the others join unawares). The arguments travel through the cluster's
    key-value store, which needs no devices."""
    import jax
    check_local_devices()
    if coordinator is None:        # a launcher's environment: the same for every process
        return
    from jax._src import distributed as jax_distributed
    client = jax_distributed.global_state.client
    mine = json.dumps({"num_processes": num_processes, "coordinator": coordinator})
    client.key_value_set(f"diffpen/join/{jax.process_index()}", mine)
    every = [json.loads(client.blocking_key_value_get(f"diffpen/join/{i}",
                                                      int(timeout_s) * 1000))
             for i in range(jax.process_count())]
    differ = []
    for field, what in (("num_processes", "numbers of processes (num_processes, "
                                          "--num-processes)"),
                        ("coordinator", "coordinators (coordinator, --coordinator)")):
        values = [e[field] for e in every]
        if len(set(values)) > 1:
            differ.append(f"{what}: " + ", ".join(
                f"{v!r} on process {i}" for i, v in enumerate(values)))
    if differ:
        raise ValueError(
            f"the {jax.process_count()} processes that joined the cluster were given "
            f"different {'; and '.join(differ)}: give every process the same coordinator and "
            f"number of processes (and its own id).")


def jaxpr_digest(closed) -> bytes:
    """SHA-256 of what a traced function computes: ``closed`` is a ``jax.core.ClosedJaxpr``
    (``jax.make_jaxpr(f)(*args)`` or ``jax.jit(f).trace(*args).jaxpr``). Its printed form
    (the operations, shapes, dtypes, literals such as dt and step counts, the names of
    custom derivative rules) and every constant it closes over (dtype, shape, bytes) are
    hashed, so two processes given functions that compute differently get different
    digests; Python code that traces to the same operations gets the same one."""
    h = hashlib.sha256(str(closed.jaxpr).encode())
    for c in closed.consts:
        a = np.asarray(c)
        h.update(str((a.dtype, a.shape)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.digest()


def _say_waiting(who: str, timeout_s, where: str) -> None:
    """One line on standard error before :func:`join` waits for the cluster."""
    sys.stderr.write(f"{who} waits up to {int(timeout_s)} s for every process to join the "
                     f"cluster through {where}\n")
    sys.stderr.flush()


def process_count() -> int:
    """Processes in the cluster (1 when running alone)."""
    import jax
    return jax.process_count()


def is_writer() -> bool:
    """True on the one process that writes output files (process 0)."""
    import jax
    return jax.process_index() == 0


def _broadcast_bytes(data: bytes) -> bytes:
    """Process 0's ``data`` on every process (others pass anything)."""
    from jax.experimental import multihost_utils
    size = int(multihost_utils.broadcast_one_to_all(np.array(len(data), np.int32)))
    buf = np.zeros(size, np.uint8)
    if is_writer():
        buf[:] = np.frombuffer(data, np.uint8)
    return np.asarray(multihost_utils.broadcast_one_to_all(buf)).tobytes()


def from_process_zero(fn: Callable):
    """``fn()`` evaluated on process 0 only (e.g. reading a file that only process 0 wrote),
    its result (picklable) returned on every process; an exception it raises is raised on
    every process (none waits for the others forever). Alone: just ``fn()``."""
    if process_count() == 1:
        return fn()
    check_local_devices()
    data = b""
    if is_writer():
        try:
            data = pickle.dumps((True, fn()))
        except Exception as exc:      # raised on every process, not only on process 0
            try:
                data = pickle.dumps((False, exc))
            except Exception:
                data = pickle.dumps((False, RuntimeError(f"on process 0: {exc!r}")))
    ok, value = pickle.loads(_broadcast_bytes(data))
    if not ok:
        raise value
    return value


def check_same(what: str, data: bytes) -> None:
    """Raise the same ``ValueError`` on every process unless all processes pass equal
    ``data`` (e.g. a digest of the work each was given): a cluster must run one program."""
    if process_count() == 1:
        return
    check_local_devices()
    from jax.experimental import multihost_utils
    digest = np.frombuffer(hashlib.sha256(data).digest(), np.uint8)
    every = np.asarray(multihost_utils.process_allgather(digest))
    differ = [i for i in range(every.shape[0]) if not np.array_equal(every[i], every[0])]
    if differ:
        raise ValueError(f"processes {differ} were given a different {what} from process 0: "
                         "start every process of a cluster with the same arguments.")
