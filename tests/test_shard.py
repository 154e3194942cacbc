"""Sharded sweeps: identical results on 4 (forced host) devices and on one."""
import textwrap

import numpy as np

from device_subprocess import run_on_devices

SCRIPT = textwrap.dedent("""
    import json
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    import diffpen as dp
    from tuning.shard import sharded_map

    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.5))
    scene.add_plane()
    sim = dp.compile(scene, dt=1e-3)

    def final(k, c):
        traj = sim.rollout(sim.params(k=k, c=c), steps=500, save_every=500)
        return {"z": traj.position[-1, 0, 2], "v": traj.velocity[-1, 0, 2]}

    ks = jnp.geomspace(2e3, 5e4, 10)           # 10 candidates: not a multiple of 4 devices
    cs = jnp.linspace(2.0, 60.0, 10)
    run = sharded_map(final)
    out = run(ks, cs)
    ref = jax.jit(jax.vmap(final))(ks, cs)
    loop = [float(final(k, c)["z"]) for k, c in zip(ks, cs)]
    # a whole sweep through tuning.sweep (sharded by default) equals the plain vmap sweep
    from tuning import sweep as sw
    pts = np.stack([np.asarray(ks), np.asarray(cs)], 1)
    names = ["contact.default.k", "contact.default.c"]
    metrics = lambda p: {"z": sim.rollout(p, steps=500, save_every=500).position[-1, 0, 2]}
    p0 = sim.params(k=1e4, c=10.0)
    sharded = sw.sweep(metrics, p0, pts, names, chunk=6, progress=False)
    single = sw.sweep(metrics, p0, pts, names, chunk=6, progress=False,
                      batch_map=lambda f: jax.jit(jax.vmap(f)))
    print(json.dumps({
        "sweep_diff": float(np.max(np.abs(sharded.metrics["z"] - single.metrics["z"]))),
        "devices": jax.device_count(),
        "mesh": int(run.mesh.devices.size),
        "max_diff": float(jnp.max(jnp.abs(out["z"] - ref["z"]))
                          + jnp.max(jnp.abs(out["v"] - ref["v"]))),
        "loop_diff": float(np.max(np.abs(np.asarray(out["z"]) - np.array(loop)))),
        "n": int(out["z"].shape[0]),
    }))
""")


def test_sharded_sweep_matches_single_device_on_four_devices():
    res = run_on_devices(SCRIPT, devices=4)
    assert res["devices"] == 4 and res["mesh"] == 4
    assert res["n"] == 10
    assert res["max_diff"] == 0.0
    assert res["loop_diff"] < 1e-12
    assert res["sweep_diff"] == 0.0


CLUSTER_SCRIPT = textwrap.dedent("""
    import json, os, tempfile
    import jax
    jax.config.update("jax_enable_x64", True)
    from tuning import distributed
    n_proc = int(os.environ["CLUSTER_PROCESSES"])
    joined = distributed.join(os.environ["CLUSTER_COORDINATOR"] or None if n_proc > 1
                              else None, n_proc if n_proc > 1 else None,
                              int(os.environ["CLUSTER_ID"]) if n_proc > 1 else None,
                              timeout_s=60)
    import jax.numpy as jnp
    import numpy as np
    import diffpen as dp
    from tuning import sweep as sw
    from tuning.batch_fit import BatchFitter
    from tuning.shard import sharded_map

    import tuning.sweep_files as files
    writes = []
    write = files.atomic_write     # every file a sweep writes (.npz and .csv)
    files.atomic_write = lambda *a, **k: (writes.append(jax.process_index()), write(*a, **k))[1]

    scene = dp.Scene()
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.0, 0.0, 0.15))
    scene.add_plane()
    sim = dp.compile(scene, dt=2e-3)

    def final(p):
        s = sim.rollout(p, steps=60, save_every=60)
        return {"z": s.position[-1, 0, 2], "v": s.velocity[-1, 0, 2]}

    # a 3 x 3 grid in chunks of 4: three chunks, the last padded
    ks, cs = np.geomspace(2e3, 2e4, 3), np.linspace(2.0, 20.0, 3)
    axes = {"contact.default.k": ks, "contact.default.c": cs}
    pts, shape = sw.grid_points(axes)
    names = list(axes)
    out = os.path.join(tempfile.mkdtemp() if n_proc == 1 else
                       os.environ["CLUSTER_TMP"], "sweep.npz")
    p0 = sim.params(k=1e4, c=10.0)
    ev = sw.make_evaluator(final, p0, names)
    res = sw.sweep(final, p0, pts, names, chunk=4, out=out, progress=False, evaluate=ev)
    again = sw.sweep(final, p0, pts, names, chunk=4, out=out, progress=False, evaluate=ev)
    saved = sw.load_sweep(out) if jax.process_index() == 0 else None

    # the README's snippet
    final_height = lambda k, c: sim.rollout(sim.params(k=k, c=c), 60,
                                            save_every=60).position[-1, 0, 2]
    heights_run = sharded_map(final_height)
    heights = heights_run(jnp.geomspace(1e3, 1e5, 6), jnp.full(6, 20.0))

    # batched fits: 4 rows (divide 4 devices evenly) and 3 (do not)
    fitter = BatchFitter(lambda p: {"z": final(p)["z"]}, p0, maxiter=4)
    fits = {n: fitter([{"z": 0.08 + 0.004 * i} for i in range(n)],
                      starts=[{"contact.default.k": 3e3 * (i + 1)} for i in range(n)])
            for n in (4, 3)}
    # a scene file's sweep (diffpen sweep SCENE.toml): the bounce of its sphere
    from tuning.scene_sweep import sweep_scene_file
    sweep_writes = list(writes)
    sdir = tempfile.mkdtemp()                 # every process has the file, none shares it
    spath = os.path.join(sdir, "ball.toml")
    with open(spath, "w") as fh:
        fh.write("dt = 2e-3\\nduration = 0.8\\n[[spheres]]\\nradius = 0.1\\nmass = 1.0\\n"
                 "position = [0.0, 0.0, 0.3]\\n[[planes]]\\n[fit]\\n"
                 "params = ['contact.default.k', 'contact.default.c']\\n[fit.bounds]\\n"
                 "'contact.default.k' = [2e3, 2e4]\\n'contact.default.c' = [2.0, 20.0]\\n")
    sres, _ = sweep_scene_file(spath, (), None, n=[3], chunk=4,
                               out=os.path.join(os.path.dirname(out), "scene.npz"))
    scene_apex = sres.metrics["apex_heights"][:, 0].tolist()     # every first apex is there

    try:                      # process 0's error reaches every process: none hangs
        distributed.from_process_zero(lambda: 1 / 0)
        raised = None
    except ZeroDivisionError as exc:
        raised = type(exc).__name__
    try:                      # processes given different work all stop with one error
        distributed.check_same("sweep", str(jax.process_index()).encode())
        differ = None
    except ValueError as exc:
        differ = str(exc)
    # process 1 given other work than process 0, each with the programs compiled above: the
    # sweep's chunk, an out= on one process only, a batched fit's targets, a sharded batch;
    # and other functions on process 1 only (61 steps instead of 60, another optimiser): a
    # sweep's metrics function, a sharded function, a batched fit's metrics and optimiser
    other, mismatch = jax.process_index(), {}

    def final61(p):
        s = sim.rollout(p, steps=61, save_every=61)
        return {"z": s.position[-1, 0, 2], "v": s.velocity[-1, 0, 2]}
    import optax
    rows3 = [{"z": 0.08 + 0.004 * i} for i in range(3)]
    starts3 = [{"contact.default.k": 3e3 * (i + 1)} for i in range(3)]
    ev61 = sw.make_evaluator(final61, p0, names) if other else ev
    heights61 = sharded_map(lambda k, c: sim.rollout(sim.params(k=k, c=c), 61, save_every=61)
                            .position[-1, 0, 2]) if other else heights_run
    fit61 = BatchFitter(lambda p: {"z": final61(p)["z"]}, p0, maxiter=4) if other else fitter
    from tuning.optimise import default_optimizer
    fit_opt = BatchFitter(lambda p: {"z": final(p)["z"]}, p0, maxiter=4,     # a custom one
                          optimizer=optax.sgd(0.05) if other else default_optimizer(0.05))
    for name, call in (
            ("chunk", lambda: sw.sweep(final, p0, pts, names, chunk=4 + other,
                                       progress=False, evaluate=ev)),
            ("out", lambda: sw.sweep(final, p0, pts, names, chunk=4, progress=False,
                                     evaluate=ev, key={"metric": "z"}, out=None if other
                                     else os.path.join(tempfile.mkdtemp(), "o.npz"))),
            ("fit", lambda: fitter([{"z": 0.08 + 0.004 * i + 0.001 * other}
                                    for i in range(3)],
                                   starts=[{"contact.default.k": 3e3 * (i + 1)}
                                           for i in range(3)])),
            ("map", lambda: heights_run(jnp.geomspace(1e3, 1e5, 6) * (1 + other),
                                        jnp.full(6, 20.0))),
            ("sweep_fn", lambda: sw.sweep(final61 if other else final, p0, pts, names, chunk=4,
                                          progress=False, evaluate=ev61)),
            ("map_fn", lambda: heights61(jnp.geomspace(1e3, 1e5, 6), jnp.full(6, 20.0))),
            ("fit_fn", lambda: fit61(rows3, starts=starts3)),
            ("fit_optimizer", lambda: fit_opt(rows3, starts=starts3))):
        if name == "fit_optimizer" and n_proc == 1:     # (not compiled alone: only compared)
            continue
        try:
            call()
            mismatch[name] = None
        except ValueError as exc:
            mismatch[name] = str(exc)
    print(json.dumps({
        "raised": raised, "differ": differ, "mismatch": mismatch,
        "joined": joined, "processes": jax.process_count(), "devices": jax.device_count(),
        "writes": sweep_writes, "scene_apex": scene_apex,
        "scene_writes": writes[len(sweep_writes):],
        "evaluated": [res.evaluated, again.evaluated],
        "z": res.metrics["z"].tolist(), "v": res.metrics["v"].tolist(),
        "again_z": again.metrics["z"].tolist(), "done": bool(again.done.all()),
        "saved_z": None if saved is None else saved.metrics["z"].tolist(),
        "heights_type": type(heights).__name__,
        "heights": np.asarray(heights).tolist(),
        "fits": {str(n): {"values": f.values.tolist(), "loss": f.loss.tolist(),
                          "history": f.loss_history.tolist(),
                          "iterations": f.iterations.tolist(), "devices": f.devices}
                 for n, f in fits.items()},
    }))
""")


def test_two_processes_gather_the_single_process_results(tmp_path):
    """Two local processes of two devices each, joined through a localhost coordinator: the
    sweep, a scene file's sweep, the README's sharded_map snippet and batched fits (rows that
    divide the 4 devices and rows that do not) return, on both processes, the single-process
    results bit for bit;
    only process 0 writes the sweep file, and a rerun resumes from it on both. Processes
    given other work (a sweep's chunk, an out= on one only, a batched fit's targets, a
    sharded batch) all stop with the same error, and so do processes given functions that
    compute something else (a sweep's metrics function, a sharded function, a batched fit's
    metrics function or optimiser: their rows were mixed unnoticed)."""
    from device_subprocess import run_cluster
    import os
    os.environ["CLUSTER_TMP"] = str(tmp_path)
    try:
        *procs, alone = run_cluster(CLUSTER_SCRIPT, processes=2, devices=2, timeout=120,
                                    alone=True)
    finally:
        del os.environ["CLUSTER_TMP"]
    assert alone["processes"] == 1 and alone["devices"] == 1 and not alone["joined"]
    assert alone["differ"] is None
    assert alone["mismatch"] == {"chunk": None, "out": None, "fit": None, "map": None,
                                 "sweep_fn": None, "map_fn": None, "fit_fn": None}
    assert alone["evaluated"] == [9, 0]
    for i, r in enumerate(procs):
        assert r["joined"] and r["processes"] == 2 and r["devices"] == 4
        # process 0 only (after its chunks, as often as their cost allows, and at the end;
        # then the fully resumed rerun writes the pair once more)
        assert (r["writes"] and set(r["writes"]) == {0}) if i == 0 else r["writes"] == []
        assert r["evaluated"] == [9, 0] and r["done"]            # the rerun resumed everything
        assert r["raised"] == "ZeroDivisionError"
        assert "processes [1] were given a different sweep" in r["differ"]
        # other work on process 1: the same error on both, before rows of one process's work
        # were returned as the other's (or the cluster hung)
        # a function computing something else on process 1 (processes mixed their rows)
        for name, words in (("chunk", "different chunk"), ("out", "different out"),
                            ("fit", "different batched fit (targets, starts and settings)"),
                            ("map", "different sharded_map batch"),
                            ("sweep_fn", "different sweep (key and points)"),
                            ("map_fn", "different sharded_map function (compared by its jaxpr"),
                            ("fit_fn", "different batched fit program (the metrics function, "
                                       "the optimiser and the fit loop, compared by their "
                                       "jaxpr)"),
                            ("fit_optimizer", "different batched fit program (the metrics")):
            assert "processes [1] were given a " + words in (r["mismatch"][name] or ""), name
        assert r["mismatch"] == procs[0]["mismatch"]
        for key in ("z", "v", "again_z", "heights", "scene_apex"):
            assert r[key] == alone[key], key                     # bit for bit (exact floats)
        assert (set(r["scene_writes"]) == {0} if i == 0 else r["scene_writes"] == [])
        for n in ("4", "3"):
            assert r["fits"][n].pop("devices") == 4 and alone["fits"][n]["devices"] == 1
            r["fits"][n]["devices"] = 1
            assert r["fits"][n] == alone["fits"][n], n
    assert procs[0]["saved_z"] == alone["z"]
    assert all(np.isfinite(alone["z"])) and len(set(alone["heights"])) == 6
    assert all(np.isfinite(alone["scene_apex"])) and len(set(alone["scene_apex"])) == 9


def test_cluster_arguments_are_checked_before_anything_runs(capsys):
    """Incomplete or inconsistent cluster flags: a clear error, exit status 2, no JAX setup."""
    import pytest

    from tuning import distributed
    from tuning.cli import main
    for argv, words in ((["--coordinator", "localhost:1234"], "all three"),
                        (["--coordinator", "localhost", "--num-processes", "2",
                          "--process-id", "0"], "HOST:PORT"),
                        (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"],
                         "[0, 1]")):
        assert main(["sweep", "--n", "2", *argv]) == 2
        assert words in capsys.readouterr().err
    with pytest.raises(ValueError, match="all three"):
        distributed.join("localhost:1234")
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        distributed.join("localhost:1234", 2, 5)
    assert distributed.join("localhost:1234", 1, 0) is False     # one process: nothing to join
    # a process silent this long stops the others: min(timeout, 10 s), at least 2 s
    assert [distributed.heartbeat_seconds(t) for t in (300, 10, 3, 1)] == [10, 10, 3, 2]
    with pytest.raises(ValueError, match="timeout_s must be a number of seconds >= 1"):
        distributed.join("localhost:1234", 2, 0, timeout_s=0)
    with pytest.raises(SystemExit):
        main(["sweep", "--n", "2", "--cluster-timeout", "0"])
    assert "--cluster-timeout must be an integer >= 1" in capsys.readouterr().err


def test_a_command_ending_on_an_error_in_a_cluster_says_so(monkeypatch, capsys):
    """A ``diffpen`` command that returns a non-zero status in a cluster marks its process
    failed (so that the others stop at once instead of waiting in a collective for it), with
    the command's status as its exit status; outside a cluster nothing is marked."""
    from tuning import distributed
    from tuning.cli import main
    argv = ["sweep", "--n", "2", "--coordinator", "localhost:1234"]    # exits with status 2
    monkeypatch.setattr(distributed, "_failure", [])
    assert main(argv) == 2 and distributed._failure == []              # not in a cluster
    monkeypatch.setattr(distributed, "_watching", [True])             # as once joined
    assert main(argv) == 2
    assert distributed._failure == [("diffpen sweep exited with status 2", 2)]
    capsys.readouterr()


def test_cluster_launchers_are_detected(monkeypatch):
    from tuning import distributed
    for var in ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_NTASKS", "SLURM_PROCID",
                "SLURM_LOCALID", "OMPI_MCA_orte_hnp_uri", "OMPI_COMM_WORLD_SIZE"):
        monkeypatch.delenv(var, raising=False)
    assert distributed.detect() is None
    slurm = dict(SLURM_JOB_ID="7", SLURM_STEP_NODELIST="node[1-2]", SLURM_NTASKS="1",
                 SLURM_PROCID="0", SLURM_LOCALID="0")
    for k, v in slurm.items():
        monkeypatch.setenv(k, v)
    assert distributed.detect() is None           # one task: nothing to join
    monkeypatch.setenv("SLURM_NTASKS", "2")
    assert distributed.detect() == "slurm"
    for k in slurm:
        monkeypatch.delenv(k)
    monkeypatch.setenv("OMPI_MCA_orte_hnp_uri", "1.0;tcp://10.0.0.1:1234")
    monkeypatch.setenv("OMPI_COMM_WORLD_SIZE", "4")
    assert distributed.detect() == "ompi"


def test_cluster_sweeps_that_cannot_run_stop_every_process(tmp_path):
    """Two 2-process ``diffpen sweep`` clusters that cannot run, started together: a scene
    file's sweep given another --chunk on process 1 (process 0 wrote rows of other points
    and process 1 hung), and a sweep whose process 0 cannot write its --out (process 0 stopped
    before joining and process 1 waited, silent, for 300 s). Every process stops at once with
    the same error, each first says on standard error what it waits for, and the scene
    file's sweep imports diffpen before joining (JAX's backend started first and diffpen
    warned that batched rollouts run slower). A third cluster, started with them, runs
    ``diffpen sweep --json``: process 0's standard output is one JSON object (the cluster
    transport's "[Gloo] Rank 0 is connected" line came first, so ``json.load`` failed) and
    process 1 prints nothing there."""
    import json
    import subprocess
    import sys

    from device_subprocess import _env, free_port, kill_left
    (tmp_path / "a").mkdir()
    scene = tmp_path / "ball.toml"
    scene.write_text("dt = 2e-3\nduration = 0.4\n[[spheres]]\nradius = 0.1\nmass = 1.0\n"
                     "position = [0.0, 0.0, 0.3]\n[[planes]]\n[fit]\n"
                     "params = ['contact.default.k', 'contact.default.c']\n[fit.bounds]\n"
                     "'contact.default.k' = [2e3, 2e4]\n'contact.default.c' = [2.0, 20.0]\n")
    chunk = [str(scene), "--n", "2", "--json", "--out", str(tmp_path / "a" / "s.npz")]
    ball = ["--n", "2", "--duration", "0.4", "--dt", "2e-3", "--json"]
    runs = {"chunk": [chunk + ["--chunk", "4"], chunk + ["--chunk", "2"]],
            "out": [ball + ["--out", str(tmp_path / "missing" / "s.npz")],
                    ball + ["--out", str(tmp_path / "s.npz")]],
            # regression: process 1's own --out was ignored without a word (process 0 wrote)
            "outs": [ball + ["--out", str(tmp_path / "s.npz")],
                     ball + ["--out", str(tmp_path / "t.npz")]],
            "json": [ball + ["--out", str(tmp_path / "j.npz")]] * 2}
    procs = {}
    for name, argvs in runs.items():
        coordinator = f"localhost:{free_port()}"
        procs[name] = [subprocess.Popen(
            [sys.executable, "-m", "tuning.cli", "sweep", *argv, "--coordinator", coordinator,
             "--num-processes", "2", "--process-id", str(i), "--cluster-timeout", "60"],
            env=_env(1), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for i, argv in enumerate(argvs)]
    try:
        outs = {name: [p.communicate(timeout=90) for p in ps] for name, ps in procs.items()}
    finally:
        kill_left([p for ps in procs.values() for p in ps])
    errors = {"chunk": "processes [1] were given a different chunk (points per call, "
                       "diffpen sweep --chunk) from process 0",
              "out": f"--out {tmp_path / 'missing' / 's.npz'}: the folder",
              "outs": "processes [1] were given a different set of output options (--out, "
                      "--plot, --fresh, --json) from process 0"}
    (j0, j1), ((out0, err0), (out1, err1)) = procs.pop("json"), outs.pop("json")
    assert [j0.returncode, j1.returncode] == [0, 0], err0[-2000:] + err1[-2000:]
    assert json.loads(out0)["points"] == 4 and out1.strip() == ""
    for name, ps in procs.items():
        for i, (p, (out, err)) in enumerate(zip(ps, outs[name])):
            assert p.returncode == 2 and out.strip() == "", (name, i, err[-2000:])
            assert f"process {i} of 2 waits up to 60 s for every process to join the " \
                   "cluster through the coordinator localhost:" in err, (name, i, err[-2000:])
            assert errors[name] in err, (name, i, err[-2000:])
            assert "backend started before" not in err, (name, i, err[-2000:])
    assert not (tmp_path / "a" / "s.npz").exists() and not (tmp_path / "s.npz").exists()
    assert "Only process 0 writes: here --out differs" in outs["outs"][1][1]
    assert not (tmp_path / "t.npz").exists()
