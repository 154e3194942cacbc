"""Sharded sweeps: identical results on 4 (forced host) devices and on one."""
import textwrap

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
