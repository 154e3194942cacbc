"""The columns layout (diffpen.layout): rollouts that step positions and velocities as three
(n,) arrays give the rows layout's values bit for bit, under jit, vmap and jacfwd, and scenes
or integrators that cannot step in columns are refused with a clear error."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffpen as dp


def _scene():
    # a ball thrown at a wall and bouncing on the ground: two plane contacts, one of them
    # with a normal along x, so every component carries a force at some point
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_sphere(radius=0.1, mass=1.0, position=(0.2, 0.0, 0.6), velocity=(0.8, 0.1, 0.0))
    scene.add_plane()
    scene.add_plane(normal=(-1.0, 0.0, 0.0), offset=-0.5)
    return scene


@pytest.fixture(scope="module")
def sims():
    return {(integ, lay): dp.compile(_scene(), dt=1e-3, integrator=integ, layout=lay)
            for integ in ("semi_implicit_euler", "verlet", "rk4")
            for lay in ("rows", "columns")}


@pytest.mark.parametrize("integ", ["semi_implicit_euler", "verlet", "rk4"])
def test_columns_rollout_equals_rows_bit_for_bit(sims, integ):
    rows, cols = sims[integ, "rows"], sims[integ, "columns"]
    assert cols.columns and not rows.columns
    p = rows.params(k=2e4, c=15.0)
    a, b = rows.rollout(p, steps=400, save_every=4), cols.rollout(p, steps=400, save_every=4)
    assert b.position.shape == a.position.shape == (100, 1, 3)
    if integ == "rk4":
        # same operations; XLA at -O0 (the tests' setting, tests/conftest.py) rounds one of
        # rk4's stage sums differently in the two programs: within 2 ulp (bit for bit at -O3)
        np.testing.assert_array_max_ulp(np.asarray(b.position), np.asarray(a.position), 2)
        np.testing.assert_array_max_ulp(np.asarray(b.velocity), np.asarray(a.velocity), 2)
    else:
        np.testing.assert_array_equal(np.asarray(b.position), np.asarray(a.position))
        np.testing.assert_array_equal(np.asarray(b.velocity), np.asarray(a.velocity))
    # the rollout did touch both planes (otherwise the test would not test the force columns)
    assert float(a.position[:, 0, 2].min()) < 0.1 and float(a.position[:, 0, 0].max()) > 0.4


def test_columns_vmap_and_forward_gradient_equal_rows(sims):
    rows, cols = sims["semi_implicit_euler", "rows"], sims["semi_implicit_euler", "columns"]

    def final(sim):
        def f(k, c):
            traj = sim.rollout(sim.params(k=k, c=c), steps=300, save_every=300)
            return traj.position[-1, 0]
        return jax.jit(jax.vmap(jax.jacfwd(f, argnums=(0, 1))))
    ks, cs = jnp.array([1e4, 3e4]), jnp.array([10.0, 30.0])
    ga, gb = final(rows)(ks, cs), final(cols)(ks, cs)
    for x, y in zip(ga, gb):
        assert np.all(np.isfinite(np.asarray(x)))
        np.testing.assert_array_equal(np.asarray(y), np.asarray(x))
    obs = jax.vmap(lambda k: cols.rollout(cols.params(k=k, c=20.0), steps=300,
                                          observe=lambda s: s.position[0, 2]).observed)(ks)
    ref = jax.vmap(lambda k: rows.rollout(rows.params(k=k, c=20.0), steps=300,
                                          save_every=1).position[:, 0, 2])(ks)
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(ref))


def test_columns_refused_with_what_stands_in_the_way():
    two = dp.Scene()
    two.add_sphere(0.1, 1.0, (0.0, 0.0, 0.5))
    two.add_sphere(0.1, 1.0, (0.0, 0.0, 0.8))
    two.add_plane()
    with pytest.raises(dp.SceneError, match="contact_sphere_sphere"):
        dp.compile(two, 1e-3, layout="columns")
    with pytest.raises(dp.SceneError, match="implicit_euler"):
        dp.compile(_scene(), 1e-3, integrator="implicit_euler", layout="columns")
    box = dp.Scene()
    box.add_box((0.1, 0.1, 0.1), 1.0, (0.0, 0.0, 0.5))
    box.add_plane()
    with pytest.raises(dp.SceneError, match="rotating bodies"):
        dp.compile(box, 1e-3, layout="columns")
    with pytest.raises(dp.SceneError, match="layout must be one of"):
        dp.compile(_scene(), 1e-3, layout="soa")


def test_auto_layout_takes_columns_wherever_a_scene_allows_them():
    """layout="auto" (the default) steps in columns when nothing stands in the way, and in
    rows otherwise (rotating bodies, an implicit integrator), never refusing a scene."""
    assert dp.compile(_scene(), dt=1e-3).layout == "columns"
    assert dp.compile(_scene(), dt=1e-3, layout="rows").layout == "rows"
    assert dp.compile(_scene(), dt=1e-3, integrator="implicit_euler").layout == "rows"
    box = dp.Scene()
    box.add_box(half_extents=(0.05, 0.05, 0.05), mass=0.37, position=(0.0, 0.0, 0.3))
    box.add_plane()
    assert dp.compile(box, dt=1e-3).layout == "rows"
    with pytest.raises(dp.SceneError, match="rotating bodies"):
        dp.compile(box, dt=1e-3, layout="columns")


def test_a_batched_rollout_loop_is_one_kernel():
    """diffpen raises XLA CPU's small-loop limit (diffpen.SMALL_LOOP_BYTES): a batched
    rollout's loop is compiled into one call instead of launching each fusion of its body
    once per step (at XLA's 1 kB default a batch of 1024 balls stepped 2.4x slower in
    columns)."""
    import os
    flags = os.environ.get("XLA_FLAGS", "")
    if os.environ.get("DIFFPEN_KEEP_XLA_FLAGS") == "1" or (
            "xla_cpu_small_while_loop_byte_threshold" not in flags):
        pytest.skip("XLA_FLAGS set by the caller")
    sim = dp.compile(_scene(), dt=1e-3, dtype=jnp.float32)
    ks = jnp.linspace(5e3, 2e4, 1024, dtype=jnp.float32)
    f = jax.jit(jax.vmap(lambda k: sim.rollout(sim.params(k=k, c=20.0), 64,
                                               save_every=64).position[-1, 0, 2]))
    text = f.lower(ks).compile().as_text()
    assert "xla_cpu_small_call" in text


def _fresh_python(code):
    """``(stdout, stderr)`` of a new Python process (every warning shown) running ``code``
    without the caller's XLA_FLAGS or DIFFPEN_KEEP_XLA_FLAGS."""
    import os
    import subprocess
    import sys
    base = {k: v for k, v in os.environ.items()
            if k not in ("XLA_FLAGS", "DIFFPEN_KEEP_XLA_FLAGS")}
    done = subprocess.run([sys.executable, "-W", "always", "-c", code], env=base,
                          capture_output=True, text=True, check=True)
    return done.stdout, done.stderr


@pytest.fixture(scope="module")
def imported_first():
    """A fresh process that imports diffpen before any JAX computation, then runs one, and
    prints XLA_FLAGS: ``(stdout, stderr)``. Both tests below read it (one process start,
    ~2 s of CPU, instead of one each): the flags diffpen set at import, and no warning."""
    return _fresh_python("import os, diffpen, jax.numpy as jnp; "
                         "jnp.ones(3).block_until_ready(); "
                         "print(os.environ.get('XLA_FLAGS', ''))")


def test_xla_flags_set_at_import_respect_the_callers(monkeypatch, imported_first):
    import os
    # a fresh process importing diffpen gets the option
    mine = imported_first[0].strip()
    assert (f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold="
            f"{dp.SMALL_LOOP_BYTES}") in mine

    # the callers' own settings: what import runs (diffpen._configure_xla_cpu), in this
    # process with its backend taken as not started
    monkeypatch.setattr(dp, "_backend_started", lambda: False)

    def flags(**env):
        for k in ("XLA_FLAGS", "DIFFPEN_KEEP_XLA_FLAGS"):
            monkeypatch.delenv(k, raising=False)
        for k, v in env.items():
            monkeypatch.setenv(k, v)
        dp._configure_xla_cpu()
        return os.environ.get("XLA_FLAGS", "").strip()
    assert flags() == mine
    # the caller's own backend options are kept, ours added to them (they were dropped)
    theirs = flags(XLA_FLAGS="--xla_backend_extra_options=foo=1")
    assert (f"--xla_backend_extra_options=foo=1,xla_cpu_small_while_loop_byte_threshold="
            f"{dp.SMALL_LOOP_BYTES}") in theirs.split()
    own = flags(XLA_FLAGS="--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=5")
    assert "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=5" in own.split()
    assert str(dp.SMALL_LOOP_BYTES) not in own
    assert flags(XLA_FLAGS="--xla_dump_hlo_pass_re=x", DIFFPEN_KEEP_XLA_FLAGS="1") == \
        "--xla_dump_hlo_pass_re=x"


def test_importing_diffpen_after_jax_started_warns(imported_first):
    """Regression: after any JAX computation the backend has read XLA_FLAGS, so the options
    diffpen sets at import (one-kernel rollout loops) silently did not apply (a batch of 4096
    balls ran 2.9x slower, XLA_FLAGS still showing them). Now a PerformanceWarning says to
    import diffpen first; importing it first warns nothing (the ``imported_first`` process:
    diffpen, then a JAX computation)."""
    late = _fresh_python("import jax.numpy as jnp; jnp.ones(3).block_until_ready(); "
                         "import diffpen")[1]
    assert "PerformanceWarning" in late and "Import diffpen before any JAX" in late
    assert "PerformanceWarning" not in imported_first[1]


def test_columns_rollouts_save_columns_and_turn_them_into_rows_once():
    """A columns rollout saves each state as columns and makes the (saves, n, 3) rows once,
    after the loop: interleaving every saved state's columns inside the loop made the natural
    `vmap(lambda k: sim.rollout(...).position[-1, 0, 2])` 6.9x the plain floor at batch 1024
    (4.6x now; benchmarks/scale_table.py). The values are the same (the other tests here)."""
    sim = dp.compile(_scene(), dt=1e-3)
    assert sim.layout == "columns"
    jx = jax.make_jaxpr(lambda k: sim.rollout(sim.params(k=k, c=20.0), 20).position)(1e4)

    def scans(jaxpr):
        for e in jaxpr.eqns:
            if e.primitive.name == "scan":
                yield e
            for p in e.params.values():
                inner = getattr(p, "jaxpr", None)
                if inner is not None:
                    yield from scans(getattr(inner, "jaxpr", inner))
    outer = [e for e in scans(jx.jaxpr) if e.params["length"] == 20]
    assert len(outer) == 1
    saved = [v.aval.shape for v in outer[0].outvars if len(v.aval.shape) >= 2]
    assert (20, sim.n_bodies) in saved and not any(s[-1:] == (3,) for s in saved), saved
