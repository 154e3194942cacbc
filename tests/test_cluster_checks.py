"""Clusters that must not run: processes with different local device counts or given different
numbers of processes, and a process that stops mid-run. Every process stops at once with a
clear error (none mixes rows, fails with a reshape error or waits for minutes)."""
import json
import subprocess
import sys
import textwrap
import threading
import time

from device_subprocess import _env, free_port, kill_left

# joins (no diffpen, no compilation: the test stays short), then one collective
SCRIPT = textwrap.dedent("""
    import json, os, signal, sys, time
    from tuning import distributed
    pid = int(os.environ["CLUSTER_ID"])
    try:
        distributed.join(os.environ["CLUSTER_COORDINATOR"], int(os.environ["CLUSTER_PROCESSES"]),
                         pid, timeout_s=int(os.environ["CLUSTER_TIMEOUT"]))
        if str(pid) in (os.environ.get("CLUSTER_DIES"), os.environ.get("CLUSTER_RAISES")):
            print(json.dumps({"stops_at": time.time()}), flush=True)
        if os.environ.get("CLUSTER_DIES") == str(pid):
            os.kill(os.getpid(), signal.SIGKILL)        # a process killed mid-run
        if os.environ.get("CLUSTER_RAISES") == str(pid):
            raise RuntimeError("a bug on this process")  # uncaught: ends on an error
        distributed.check_same("x", b"the same")
        print(json.dumps({"error": None}), flush=True)
    except ValueError as exc:
        print(json.dumps({"error": str(exc)}), flush=True)
""")

# the same through the diffpen command's entry (its signal handlers, exit statuses and
# messages): a command "probe" joins, then process CLUSTER_SIGNALLED sends itself
# CLUSTER_SIGNAL while process 0 waits for it in a collective
SCRIPT_COMMAND = textwrap.dedent("""
    import json, os, signal, sys, time, types
    import tuning.cli as cli
    from tuning import distributed

    def run(args):
        pid = int(os.environ["CLUSTER_ID"])
        distributed.join(os.environ["CLUSTER_COORDINATOR"], int(os.environ["CLUSTER_PROCESSES"]),
                         pid, timeout_s=int(os.environ["CLUSTER_TIMEOUT"]))
        if str(pid) == os.environ["CLUSTER_SIGNALLED"]:
            print(json.dumps({"stops_at": time.time()}), flush=True)
            os.kill(os.getpid(), getattr(signal, os.environ["CLUSTER_SIGNAL"]))
            time.sleep(30)                      # the handler raises here
        distributed.check_same("x", b"the same")
        return 0
    sys.modules["cluster_probe"] = types.SimpleNamespace(add_arguments=lambda p: None, run=run)
    cli.COMMANDS["probe"] = ("cluster_probe", "a probe")
    sys.argv = ["diffpen", "probe"]
    cli.entry()
""")


def test_clusters_that_cannot_run_stop_every_process_with_a_clear_error():
    """Three 2-process clusters started together: (devices) process 0 with 2 local devices and
    process 1 with 1 (every collective failed with "cannot reshape array of size 3 into shape
    (2,2)"); (nproc) process 0 given 2 processes and process 1 given 3 (the two ran as a
    2-process cluster unnoticed); (dies) process 1 killed after joining (process 0 hung about
    100 s, then JAX aborted it, SIGABRT). The first two raise the same error on both
    processes; in the third, process 0 says that a process of the cluster stopped and exits
    with status 2 within the 3 s of silence its --cluster-timeout of 3 s allows. In a fourth,
    process 1 ends on an uncaught exception after joining while process 0 waits in a
    collective for it (process 0 waited until JAX's 300 s shutdown wait ran out): process 0
    stops at once, naming process 1's error, whatever its --cluster-timeout (30 s here)."""
    runs = {"devices": ([2, 1], [2, 2], 30, None), "nproc": ([1, 1], [2, 3], 30, None),
            "dies": ([1, 1], [2, 2], 3, "1"), "raises": ([1, 1], [2, 2], 30, None),
            "SIGINT": ([1, 1], [2, 2], 30, None), "SIGTERM": ([1, 1], [2, 2], 30, None)}
    procs = {}
    for name, (devices, counts, timeout, dies) in runs.items():
        coordinator = f"localhost:{free_port()}"
        command = name.startswith("SIG")
        procs[name] = [subprocess.Popen(
            [sys.executable, "-c", SCRIPT_COMMAND if command else SCRIPT],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=_env(devices[i], CLUSTER_COORDINATOR=coordinator,
                                CLUSTER_PROCESSES=str(counts[i]), CLUSTER_ID=str(i),
                                CLUSTER_TIMEOUT=str(timeout), CLUSTER_DIES=dies or "",
                                CLUSTER_RAISES="1" if name == "raises" else "",
                                CLUSTER_SIGNALLED="1", CLUSTER_SIGNAL=name))
            for i in range(2)]
    # each process's output and the time it ended (the clock of its own exit, not of the
    # others: eight processes importing JAX on a loaded machine take a while to start)
    done = {}

    def wait(key, p):
        try:
            done[key] = (*p.communicate(timeout=120), time.time())
        except subprocess.TimeoutExpired:
            done[key] = ("", "timed out after 120 s", time.time())
    waits = [threading.Thread(target=wait, args=((name, i), p))
             for name, ps in procs.items() for i, p in enumerate(ps)]
    try:
        for t in waits:
            t.start()
        for t in waits:
            t.join()
    finally:
        kill_left([p for ps in procs.values() for p in ps])
    outs = {name: [done[name, i][:2] for i in range(2)] for name in procs}

    def stopped_after(name):
        """Seconds from process 1's stop (it printed the time first) to process 0's exit."""
        out1 = outs[name][1][0]
        stops_at = [json.loads(line)["stops_at"] for line in out1.splitlines()
                    if line.startswith('{"stops_at"')]
        assert stops_at, (name, out1, outs[name][1][1][-2000:])
        return done[name, 0][2] - stops_at[0]
    errors = {"devices": "every process of a cluster must have the same number of local "
                         "devices, but process 0 has 2, process 1 has 1 (3 devices in all): "
                         "give every process the same devices (on CPU the same "
                         "XLA_FLAGS=--xla_force_host_platform_device_count=N",
              "nproc": "the 2 processes that joined the cluster were given different numbers "
                       "of processes (num_processes, --num-processes): 2 on process 0, 3 on "
                       "process 1: give every process the same coordinator and number of "
                       "processes"}
    for name, words in errors.items():
        for i, (p, (out, err)) in enumerate(zip(procs[name], outs[name])):
            assert p.returncode == 0, (name, i, err[-2000:])
            last = [line for line in out.splitlines() if line.startswith("{")][-1]
            assert words in json.loads(last)["error"], (name, i, out)
    (p0, p1), ((out, err), _) = procs["dies"], outs["dies"]
    assert p1.returncode == -9
    assert p0.returncode == 2, err[-3000:]
    assert "a process of the cluster stopped: process 1 of 2 has not answered for 3 s (it " \
           "was killed, crashed or froze); process 0 stops too (exit status 2)" in err, err
    assert stopped_after("dies") < 30   # JAX's default: about 100 s, then SIGABRT
    (p0, p1), ((out, err), (_, err1)) = procs["raises"], outs["raises"]
    assert p1.returncode == 1 and "RuntimeError: a bug on this process" in err1, err1[-2000:]
    assert p0.returncode == 2, err[-3000:]
    assert "a process of the cluster stopped: process 1 of 2 ended on an error (RuntimeError: " \
           "a bug on this process); process 0 stops too (exit status 2)" in err, err[-3000:]
    # well under the 30 s timeout (the old code: Gloo's deadline after it, then JAX's 300 s
    # shutdown wait)
    assert stopped_after("raises") < 20
    # a diffpen command interrupted (Ctrl-C) or terminated (SIGTERM, as SLURM at its time
    # limit) on one process: it ends with its own status and line, and the other stops
    # within seconds naming it. Before, a Ctrl-C hung both processes (the interrupted one
    # said it ended normally, and waited in JAX's shutdown for the other, which waited in
    # the collective), and SIGTERM went to JAX's preemption notifier, which logged it and
    # let the run go on.
    for sig, status, what in (("SIGINT", 130, "interrupted"), ("SIGTERM", 143, "terminated")):
        (p0, p1), ((out, err), (_, err1)) = procs[sig], outs[sig]
        assert p1.returncode == status and f"diffpen probe: {what}" in err1, (sig, err1[-2000:])
        assert p0.returncode == 2, (sig, err[-3000:])
        assert "a process of the cluster stopped: process 1 of 2 ended" in err, (sig, err)
        assert f"(diffpen probe {what})" in err and "process 0 stops too" in err, (sig, err)
        assert "ended on an error" not in err, (sig, err)      # a signal is no error
        assert "Traceback" not in err and "Gloo" not in err.split("stopped:")[0], (sig, err)
        assert stopped_after(sig) < 20, sig


def test_a_stopping_process_lets_the_files_it_is_writing_finish(monkeypatch, capsys):
    """Regression: the cluster watcher's stop (another process ended, e.g. on SIGTERM)
    exited at once, also between a sweep's .npz and its .csv, which then disagreed. It now
    waits for the block writing them (tuning.progress.uninterrupted), 30 s at most."""
    import os

    from tuning import distributed
    from tuning.progress import uninterrupted
    exits = []
    monkeypatch.setattr(os, "_exit", lambda code: exits.append((code, time.monotonic())))
    with uninterrupted():
        stopper = threading.Thread(target=distributed._stop, args=(0, "a test"))
        stopper.start()
        time.sleep(0.3)
        assert exits == []
        written = time.monotonic()
    stopper.join(5.0)
    assert exits and exits[0][0] == distributed.STOPPED_STATUS and exits[0][1] >= written
    assert "a process of the cluster stopped: a test" in capsys.readouterr().err


def test_a_second_process_zero_is_refused_before_joining():
    """Regression: two processes given process id 0 (or a coordinator port another program
    listens on) both aborted inside JAX's coordination service with a C++ stack trace and no
    word of the cause. Process 0 now checks that its coordinator port is free before JAX
    starts its service and raises a ValueError that says what to change. Here the test
    holds the port, as a first process 0 would."""
    import socket
    port = free_port()
    holder = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    holder.bind(("", port))
    holder.listen()
    try:
        run = subprocess.run(
            [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120,
            env=_env(1, CLUSTER_ID="0", CLUSTER_COORDINATOR=f"localhost:{port}",
                     CLUSTER_PROCESSES="2", CLUSTER_TIMEOUT="5"))
    finally:
        holder.close()
    assert run.returncode == 0, run.stderr[-2000:]
    error = json.loads(run.stdout.strip().splitlines()[-1])["error"]
    assert f"port {port}" in error and "process id 0 too" in error
    assert "waits up to" not in run.stderr          # refused before it waited
