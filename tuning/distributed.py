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
"""
from __future__ import annotations

import os
import pickle
import sys
from typing import Callable

import numpy as np

__all__ = ["join", "check", "detect", "parse_coordinator", "is_writer", "process_count",
           "from_process_zero", "check_same"]


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
        _say_waiting(f"process {int(process_id)} of {int(num_processes)}", timeout_s,
                     f"the coordinator {coordinator} (every process needs the same coordinator "
                     f"and number of processes, and its own id in 0..{int(num_processes) - 1})")
        jax.distributed.initialize(coordinator, int(num_processes), int(process_id),
                                   initialization_timeout=int(timeout_s))
        return True
    launcher = detect()
    if launcher is None:
        return False
    name = {"slurm": "SLURM", "ompi": "Open MPI"}.get(launcher, launcher)
    _say_waiting("this process", timeout_s, f"the coordinator that the {name} launch names")
    jax.distributed.initialize(initialization_timeout=int(timeout_s))
    return True


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
    import hashlib

    from jax.experimental import multihost_utils
    digest = np.frombuffer(hashlib.sha256(data).digest(), np.uint8)
    every = np.asarray(multihost_utils.process_allgather(digest))
    differ = [i for i in range(every.shape[0]) if not np.array_equal(every[i], every[0])]
    if differ:
        raise ValueError(f"processes {differ} were given a different {what} from process 0: "
                         "start every process of a cluster with the same arguments.")
