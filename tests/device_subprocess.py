"""Run a test script in subprocesses with forced host devices (JAX reads the device count
once, at start-up, so it cannot change inside the test process), alone or as a cluster of
local processes joined through a localhost coordinator."""
import json
import os
import socket
import subprocess
import sys
import time


def _env(devices: int, **extra) -> dict:
    """The test process's environment with ``devices`` forced CPU devices; the compile-time
    options the test process compiles with (tests/conftest.py: LLVM -O0 and XLA's classic
    emitters unless DIFFPEN_TEST_XLA_OPT=1) are passed on, since the subprocesses' time is
    their compiles."""
    flags = [f"--xla_force_host_platform_device_count={devices}"]
    flags += [f for f in os.environ.get("XLA_FLAGS", "").split()
              if f.startswith(("--xla_backend_optimization_level=",
                               "--xla_cpu_use_fusion_emitters="))]
    return dict(os.environ, XLA_FLAGS=" ".join(flags), JAX_PLATFORMS="cpu", **extra)


def run_on_devices(script: str, devices: int = 4, timeout: float = 300) -> dict:
    """Run ``script`` with ``devices`` forced CPU devices; return the JSON object it prints on
    its last line of standard output."""
    proc = subprocess.run([sys.executable, "-c", script], env=_env(devices),
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def kill_left(procs) -> None:
    """Kill and reap every process of ``procs`` (a list of Popen) still running: a cluster
    test never leaves a process behind, whatever failed."""
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()


def free_port() -> int:
    """A TCP port on localhost that nothing listens on now, below the kernel's ephemeral
    range: a port the kernel hands out (bind to port 0) could be handed out again, to a
    running cluster's gloo connections, before the coordinator given it starts listening
    ("Failed to start RPC server" when several clusters start together)."""
    import random
    low = 32768
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as fh:
            low = int(fh.read().split()[0])
    except (OSError, ValueError, IndexError):
        pass
    rng = random.Random()
    for _ in range(200):
        port = rng.randrange(10000, max(10001, low))
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("localhost", port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def run_cluster(script: str, processes: int = 2, devices: int = 2, timeout: float = 120,
                alone: bool = False) -> list:
    """Start ``processes`` copies of ``script`` (``devices`` forced CPU devices each) that join
    one cluster through a coordinator on a free localhost port; each finds its place in the
    environment variables ``CLUSTER_COORDINATOR``, ``CLUSTER_PROCESSES`` and ``CLUSTER_ID``.
    With ``alone``, one more copy runs at the same time as a single process on one device
    (``CLUSTER_PROCESSES=1``), and its output comes last. Every process is killed after
    ``timeout`` seconds (a cluster that cannot form must fail, not hang). Returns the JSON
    objects the processes print on their last line of standard output, by process id."""
    coordinator = f"localhost:{free_port()}"
    envs = [_env(devices, CLUSTER_COORDINATOR=coordinator, CLUSTER_PROCESSES=str(processes),
                 CLUSTER_ID=str(i)) for i in range(processes)]
    if alone:
        envs.append(_env(1, CLUSTER_COORDINATOR="", CLUSTER_PROCESSES="1", CLUSTER_ID="0"))
    procs = [subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for env in envs]
    outs, deadline = [], time.monotonic() + timeout
    try:
        for p in procs:
            outs.append(p.communicate(timeout=max(1.0, deadline - time.monotonic())))
    finally:
        kill_left(procs)
    for i, (p, (out, err)) in enumerate(zip(procs, outs)):
        assert p.returncode == 0, f"process {i} failed:\n{err[-3000:]}"
    return [json.loads(out.strip().splitlines()[-1]) for out, _ in outs]
