"""Fuzz: hundreds of bad library arguments and command lines (fixed seed, nothing compiled).
Each must end in a clear diffpen error -- a SceneError from the library, exit status 2 with a
message from the command line -- never a raw JAX/numpy/Python traceback and never a hang."""
import signal
import time

import numpy as np
import pytest

import diffpen as dp
from tuning.cli import main

NAN, INF = float("nan"), float("inf")
#: values that are never a valid number for any argument
NOT_A_NUMBER = ["1.0", "abc", True, False, None, [1.0, 2.0], (1.0,), {}, object(), 1j,
                np.array([1.0, 2.0]), b"1", NAN, INF, -INF]
BAD_POSITIVE = NOT_A_NUMBER + [-1.0, 0.0, -1e-300]
BAD_VEC3 = ["abc", None, True, (0.0, 0.0), (0.0, 0.0, 0.0, 0.0), (NAN, 0.0, 0.0),
            (0.0, INF, 0.0), ("0", 0.0, 1.0), (1j, 0.0, 0.0), {}, object(), 1.0]
BAD_INDEX = [-1, 99, "0", 1.5, True, None, (0,), np.float64(0.0)]
BAD_STEPS = [0, -1, 1.5, "10", True, None, 10 ** 12, np.float64(10.0), [10]]


class Hang(Exception):
    pass


@pytest.fixture
def alarm():
    def on_alarm(*_):
        raise Hang("a bad input hung for more than 10 s")
    old = signal.signal(signal.SIGALRM, on_alarm)
    yield lambda s: signal.alarm(s)
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def _scene():
    s = dp.Scene()
    s.add_sphere(0.1, 1.0, (0.0, 0.0, 1.0))
    s.add_sphere(0.1, 1.0, (1.0, 0.0, 1.0))
    s.add_plane()
    return s


def api_cases(rng, n):
    """``n`` (label, call) pairs, each call given ONE bad argument."""
    sim = dp.compile(_scene(), 1e-3)           # built once; nothing here is traced
    good = sim.params(k=1e4, c=10.0)
    s0 = sim.init_state()
    import jax.numpy as jnp
    bad_states = ["state", 1.0, s0._replace(position=jnp.zeros((3, 3))),
                  s0._replace(velocity=jnp.zeros((2, 2))),
                  s0._replace(position=s0.position.astype(jnp.float32)),
                  s0._replace(velocity=s0.velocity.at[1, 0].set(jnp.inf)),
                  s0._replace(aux={"x": jnp.zeros(())})]
    makers = [
        ("add_sphere.radius", lambda v: _scene().add_sphere(v, 1.0, (5.0, 0.0, 1.0)), BAD_POSITIVE),
        ("add_sphere.mass", lambda v: _scene().add_sphere(0.1, v, (5.0, 0.0, 1.0)), BAD_POSITIVE),
        ("add_sphere.position", lambda v: _scene().add_sphere(0.1, 1.0, v), BAD_VEC3),
        ("add_sphere.velocity", lambda v: _scene().add_sphere(0.1, 1.0, (5, 0, 1), v), BAD_VEC3),
        ("add_particle.mass", lambda v: _scene().add_particle(v, (5.0, 0.0, 1.0)), BAD_POSITIVE),
        ("add_box.half", lambda v: _scene().add_box((v, 0.1, 0.1), 1.0, (5.0, 0.0, 1.0)),
         BAD_POSITIVE),
        ("add_box.orientation", lambda v: _scene().add_box((0.1,) * 3, 1.0, (5, 0, 1),
                                                           orientation=v),
         BAD_VEC3 + [(0.0, 0.0, 0.0, 0.0)]),
        ("add_plane.normal", lambda v: _scene().add_plane(v), BAD_VEC3),
        ("add_plane.offset", lambda v: dp.Scene().add_plane(offset=v), NOT_A_NUMBER),
        ("add_fixed_sphere.radius", lambda v: _scene().add_fixed_sphere((5, 5, 5), v),
         BAD_POSITIVE),
        ("add_spring.a", lambda v: _scene().add_spring(v, 1, k=10.0), BAD_INDEX),
        ("add_spring.k", lambda v: _scene().add_spring(0, 1, k=v), BAD_POSITIVE[:-3] + [-1.0]),
        ("add_material.k", lambda v: _scene().add_material("m", k=v, c=1.0),
         NOT_A_NUMBER + [-1.0]),
        ("add_material.name", lambda v: _scene().add_material(v, k=1.0, c=1.0),
         ["", 5, None, True]),
        ("compile.dt", lambda v: dp.compile(_scene(), v), BAD_POSITIVE),
        ("compile.integrator", lambda v: dp.compile(_scene(), 1e-3, integrator=v),
         ["rk5", "", None, 4]),
        ("compile.law", lambda v: dp.compile(_scene(), 1e-3, law=v), ["hooke", None, 1]),
        ("params.k", lambda v: sim.params(k=v, c=1.0), NOT_A_NUMBER + [-1.0]),
        ("params.c", lambda v: sim.params(k=1.0, c=v), NOT_A_NUMBER + [-1.0]),
        ("params.contact", lambda v: sim.params(contact={v: (1.0, 1.0)}), ["nope", 1]),
        ("rollout.params", lambda v: sim.rollout(v, 10),
         [None, {}, 1.0, "p", (1.0, 2.0), good.contact]),
        ("rollout.steps", lambda v: sim.rollout(good, v), BAD_STEPS),
        ("rollout.save_every", lambda v: sim.rollout(good, 10, save_every=v),
         [0, 3, -1, 2.0, "2"]),          # None: the default (every state)
        ("rollout.state", lambda v: sim.rollout(good, 10, v), bad_states),
    ]
    for _ in range(n):
        label, make, pool = makers[rng.integers(len(makers))]
        v = pool[rng.integers(len(pool))]
        yield f"{label}={v!r}", (lambda make=make, v=v: make(v))


def test_api_fuzz_ends_in_clear_diffpen_errors(alarm):
    rng = np.random.default_rng(20261201)
    t0 = time.perf_counter()
    n = 0
    for label, call in api_cases(rng, 400):
        alarm(10)
        try:
            call()
        except dp.SceneError as exc:
            assert str(exc) and len(str(exc)) > 20, label
        except Exception as exc:   # noqa: BLE001 - anything else is a defect
            pytest.fail(f"{label}: raw {type(exc).__name__}: {exc}")
        else:
            pytest.fail(f"{label}: accepted")
        finally:
            alarm(0)
        n += 1
    assert n == 400 and time.perf_counter() - t0 < 60


#: per subcommand: (flag, bad values); every value is invalid for its flag
CLI_BAD = {
    "fit": [("--radius", ["-1", "0", "nan", "inf", "abc", ""]),
            ("--mass", ["-1", "0", "nan", "x"]), ("--drop", ["0", "-2", "inf"]),
            ("--target-apex", ["0", "-0.4", "nan", "x"]),
            ("--target-settle", ["0", "nan", "-3"]), ("--target-contact", ["0", "inf"]),
            ("--settle-tol", ["0", "-1e-3", "nan"]), ("--dt", ["0", "-1e-3", "nan", "1e-3s"]),
            ("--lr", ["0", "nan"]), ("--k0", ["0", "-1e4", "inf"]), ("--c0", ["0", "nan"]),
            ("--maxiter", ["0", "-3", "1.5", "many", "nan"]), ("--law", ["hooke"]),
            ("--method", ["newton"]), ("--plot", ["/proc/nope/x.png", "."]),
            ("--data", ["/proc/nope.csv", "."])],
    "simulate": [("--k", ["0", "-1", "nan", "x"]), ("--c", ["nan", "-1", "x", "inf"]),
                 ("--steps", ["0", "-1", "1e9", "x", "1000000000"]),
                 ("--dt", ["0", "nan", "x"]), ("--law", ["hooke"]),
                 ("--out", ["/proc/nope/t.npz", "."])],
    "sweep": [("--n", ["1", "0", "1.5", "x", "100000", "1e5"]),
              ("--radius", ["0", "-1", "nan"]), ("--mass", ["0", "x"]),
              ("--duration", ["1e-6", "0", "-1", "nan"]), ("--dt", ["0", "nan"]),
              ("--chunk", ["0", "x", "-5"]), ("--out", ["/proc/nope/s.npz", ".", "s.txt"]),
              ("--plot", ["/proc/nope/h.png"]), ("--target", ["nan", "inf", "x"]),
              ("--metric", ["loss"]), ("--settle-tol", ["0", "nan"])],
    "report": [("--tol", ["0", "nan"]), ("--k", ["0", "x"]), ("--c", ["nan", "-1"]),
               ("--repeats", ["0", "x"]), ("--plot", ["/proc/nope/a.png"]),
               ("--integrators", ["rk5"]), ("--height", ["0", "nan"])],
}
POSITIONAL = {"fit": [], "simulate": ["ball"], "sweep": [], "report": ["accuracy"]}


def test_cli_fuzz_exits_2_with_a_message(capsys, monkeypatch, alarm):
    import diffpen

    def boom(*a, **k):
        raise AssertionError("compiled before refusing the input")
    monkeypatch.setattr(diffpen, "compile", boom)
    monkeypatch.setenv("DIFFPEN_CACHE", "0")
    rng = np.random.default_rng(7)
    cmds = list(CLI_BAD)
    for _ in range(300):
        cmd = cmds[rng.integers(len(cmds))]
        flags = CLI_BAD[cmd]
        argv = [cmd] + POSITIONAL[cmd]
        for j in rng.choice(len(flags), size=rng.integers(1, 3), replace=False):
            flag, values = flags[j]
            argv += [flag, values[rng.integers(len(values))]]
        alarm(10)
        try:
            rc = main(argv)
        except SystemExit as exc:
            rc = exc.code
        finally:
            alarm(0)
        err = capsys.readouterr().err
        assert rc == 2, (argv, err)
        assert "error:" in err and "Traceback" not in err, (argv, err)
