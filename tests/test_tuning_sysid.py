"""Trajectory fits: recovery of known k and c from a synthetic noisy record, standard errors
that cover the truth, and clear errors for bad CSV files."""
import numpy as np
import pytest

from tuning import sysid as S
from tuning.fit import FitError

K_TRUE, C_TRUE = 1e4, 20.0


@pytest.fixture(scope="module")
def record():
    # 2 s at 500 Hz, 1 mm noise, simulated with a much finer step than the fit will use
    return S.synthetic_record(K_TRUE, C_TRUE, duration=2.0, rate=500.0, noise=1e-3,
                              dt=2e-5, seed=3)


def test_events_give_a_first_guess_within_a_few_percent(record):
    t, z = record
    ev = S.record_events(t, z, radius=0.1)
    assert ev.noise == pytest.approx(1e-3, rel=0.15)
    assert ev.apex[0] == pytest.approx(0.9, rel=2e-3)
    k, c = S.first_guess(ev, 1.0)
    assert k == pytest.approx(K_TRUE, rel=0.08) and c == pytest.approx(C_TRUE, rel=0.08)


def test_recovers_k_and_c_with_covering_standard_errors(record, monkeypatch):
    """... and builds each of its simulators once (regression: the step's choice and the fit
    built the same ones twice, so their rollouts compiled twice: `diffpen fit --data` 4.4 ->
    3.5 s)."""
    t, z = record
    built, compile_ = [], S.dp.compile
    from tuning import compiled
    monkeypatch.setattr(compiled, "_SIMS", S.ProgramCache())      # none kept from before
    monkeypatch.setattr(S.dp, "compile", lambda scene, dt, **kw: built.append(
        (scene.bodies[0].position, scene.bodies[0].velocity, dt)) or compile_(scene, dt, **kw))
    # regression: unlike the scene files' record fits it gave no float32 warning (and its
    # step-error part of the standard errors was 10x the float64 one there, unsaid)
    precisions = []
    monkeypatch.setattr(S, "warn_record_precision", precisions.append)
    res = S.fit_trajectory(t, z, radius=0.1, mass=1.0)
    assert [np.dtype(d) for d in precisions] == [np.dtype(np.float64)]
    import warnings

    from tuning.lm import warn_record_precision
    with pytest.warns(UserWarning, match=r"less reliable in float32.*counts the rounding"):
        warn_record_precision(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_record_precision(np.float64)
    assert built and len(set(built)) == len(built), built
    assert abs(res.k / K_TRUE - 1) < 0.02 and abs(res.c / C_TRUE - 1) < 0.02
    # the reported standard errors cover the truth (95 % interval)
    assert abs(res.k - K_TRUE) <= 2.0 * res.k_stderr, (res.k, res.k_stderr)
    assert abs(res.c - C_TRUE) <= 2.0 * res.c_stderr, (res.c, res.c_stderr)
    assert 0 < res.k_stderr < 0.01 * K_TRUE and 0 < res.c_stderr < 0.01 * C_TRUE
    # the residual is the noise: the model (and its dt) explains the record
    assert res.rms == pytest.approx(1e-3, rel=0.1)
    assert res.dt_error < res.noise / 6
    assert len(res.horizons) >= 2          # grown bounce by bounce


def test_a_later_record_fit_compiles_nothing(record, caplog):
    """A second record fitted in the same process at the same step (another ball's drop,
    another noise draw) runs the programs the first fit compiled: the simulators were keyed
    on the record's start height and the residual program closed over the record (2.3 s a
    record, now 0.1 s)."""
    import logging
    t, z = record
    rng = np.random.default_rng(5)
    S.fit_trajectory(t, z, radius=0.1, mass=1.0, dt=2e-4, maxiter=1, grow=False)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="jax"), S.jax.log_compiles():
        res = S.fit_trajectory(t, 0.98 * z + 1e-3 * rng.standard_normal(z.shape), radius=0.1,
                               mass=1.0, dt=2e-4, maxiter=1, grow=False)
    compiled = [r.getMessage() for r in caplog.records if r.getMessage().startswith("Compiling")]
    assert compiled == [], compiled
    assert res.events.z0 == pytest.approx(0.98, abs=5e-3)


def _write(tmp_path, text):
    p = tmp_path / "rec.csv"
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize("text, words", [
    ("", "empty"),
    ("time,height\n0,1\n", "columns 't' and 'z'"),
    ("t,z\n" + "".join(f"{i * 0.01},1.0\n" for i in range(5)), "at least 20"),
    ("t,z\n" + "".join(f"{i * 0.01},1.0\n" for i in range(30)).replace("0.05,1.0", "0.05,abc"),
     "line 7"),
    ("t,z\n" + "".join(f"{i * 0.01},1.0\n" for i in range(30)).replace("0.05,1.0", "0.05,nan"),
     "finite"),
    ("t,z\n" + "".join(f"{i * 0.01},1.0\n" for i in range(30)).replace("0.05,", "0.01,"),
     "strictly increase"),
])
def test_bad_csv_is_refused_with_the_line(tmp_path, text, words):
    with pytest.raises(FitError, match=words):
        S.load_csv(_write(tmp_path, text))


def test_csv_roundtrip_and_missing_file(tmp_path, record):
    t, z = record
    path = str(tmp_path / "r.csv")
    S.save_csv(path, t, z)
    t2, z2 = S.load_csv(path)
    np.testing.assert_array_equal(t, t2)
    np.testing.assert_array_equal(z, z2)
    with pytest.raises(FitError, match="cannot read"):
        S.load_csv(str(tmp_path / "missing.csv"))


def test_record_must_start_in_flight(record):
    t, z = record
    with pytest.raises(FitError, match="start with the ball in free flight"):
        S.record_events(t, z, radius=1.5)


# --------------------------------------------------------------------------- hard contacts
def _hard_ball(t, *, drop=1.0, e=0.7, radius=0.1, g=9.81):
    """Centre height of a ball dropped from rest at ``drop`` whose bounces are instantaneous
    (closed form: parabolas, the velocity reversed and scaled by ``e`` at each impact)."""
    z = np.empty_like(t)
    t0, z0, v0 = 0.0, drop, 0.0
    while True:
        s = (v0 + np.sqrt(v0 ** 2 + 2 * g * (z0 - radius))) / g      # to the next impact
        m = (t >= t0) & (t < t0 + s)
        z[m] = z0 + v0 * (t[m] - t0) - 0.5 * g * (t[m] - t0) ** 2
        if t0 + s > t[-1]:
            return z
        t0, z0, v0 = t0 + s, radius, e * (g * s - v0)


@pytest.mark.parametrize("rate, phase", [(100.0, 0.0), (100.0, 0.4), (200.0, 0.0),
                                         (200.0, 0.3)])
def test_bounces_between_samples_split_the_flights(rate, phase):
    """At 100-200 Hz a hard bounce leaves no sample near the floor: the flights were not
    split ("fewer than two flights"); they are now split where the velocity reverses. With
    phase 0.4 at 100 Hz and 0.3 at 200 Hz no bounce leaves a single lowest sample (the two
    samples around each are about as high)."""
    import diffpen as dp
    t = np.arange(0.0, 1.6, 1.0 / rate) + phase / rate
    z = _hard_ball(t) + 5e-4 * np.random.default_rng(1).standard_normal(t.shape)
    ev = S.record_events(t, z, radius=0.1)
    assert len(ev.apex) == 4                       # 3 bounces in 1.6 s
    assert np.all(np.abs(ev.restitution / 0.7 - 1) < 0.01), ev.restitution
    k, c = S.first_guess(ev, 1.0)
    assert float(dp.physical.restitution(k, c, 1.0)) == pytest.approx(0.7, rel=0.01)


def test_flights_too_short_for_the_frame_rate_name_the_rate():
    """A 1 m drop at 10 Hz holds bounces of at most 5 samples each: it was refused as
    holding "fewer than two flights"; the message now says the flights are too short for the
    sample rate. A record without a second flight keeps the plain message."""
    t = np.arange(0.0, 1.2, 0.1)                   # flights of at most 5 samples
    z = _hard_ball(t, e=0.5) + 5e-4 * np.random.default_rng(5).standard_normal(t.shape)
    with pytest.raises(FitError, match=r"fewer than two flights of at least 6 samples .*: 0 of "
                                       r"its \d+ flights have that many, the longest of the "
                                       r"others has [1-5], at 0.1 s between samples \(10 Hz\)"
                                       r"\. Record faster"):
        S.record_events(t, z, radius=0.1)
    t = np.arange(0.0, 0.4, 0.01)
    with pytest.raises(FitError, match=r"fewer than two flights: a trajectory fit needs"):
        S.record_events(t, _hard_ball(t), radius=0.1)


def test_noise_near_an_apex_makes_no_bounce():
    """Sharp dips at the apexes (spikes of 2 cm, far above the margin) are not bounces: a
    bounce's samples lie within a frame's travel of the floor."""
    rate = 100.0
    t = np.arange(0.0, 1.6, 1.0 / rate)
    z = _hard_ball(t) + 5e-4 * np.random.default_rng(2).standard_normal(t.shape)
    apexes = [int(np.argmax(np.where((t > a) & (t < b), z, -1.0)))
              for a, b in ((0.5, 1.0), (1.1, 1.4))]
    z[apexes] -= 0.02
    ev = S.record_events(t, z, radius=0.1)
    assert len(ev.apex) == 4, ev.apex
    assert np.all(np.abs(ev.restitution / 0.7 - 1) < 0.01), ev.restitution


@pytest.fixture(scope="module")
def hard_1khz():
    # 1 s at 1 kHz, 0.5 mm noise: both measured contact durations are noise below 0
    t = np.arange(0.0, 1.0, 1e-3)
    return t, _hard_ball(t, drop=0.6) + 5e-4 * np.random.default_rng(4).standard_normal(
        t.shape)


def test_an_unresolved_contact_time_gives_k_as_a_lower_bound(hard_1khz):
    """A hard contact at 1 kHz: the durations are noise (a few hundredths of a ms either
    side of 0). The first guess refused ("need a positive contact duration") or, with
    durations of 0.01-0.1 ms, chased k to 1e10-1e11 N/m (a minutes-long fit). Now k is held
    at the smallest stiffness the record allows, reported as a lower bound, and c is fitted."""
    import diffpen as dp
    t, z = hard_1khz
    ev = S.record_events(t, z, radius=0.1)
    k, c = S.first_guess(ev, 1.0)
    assert len(ev.apex) == 3 and np.all(ev.contact < 3 * ev.contact_resolution)
    assert 1e8 < k < 1e10
    res = S.fit_trajectory(t, z, radius=0.1, mass=1.0, maxiter=6)
    assert res.k_lower_bound == pytest.approx(k) and res.k == pytest.approx(k)
    assert res.k_stderr == np.inf and 0 < res.c_stderr < 0.05 * res.c
    assert any("LOWER BOUND" in n for n in res.notes), res.notes
    assert float(dp.physical.restitution(res.k, res.c, 1.0)) == pytest.approx(0.7, rel=0.01)
    assert res.rms == pytest.approx(5e-4, rel=0.1)           # the record is explained
    assert res.dt > 1e-6                                    # fast: ~1e5 steps, not 1e8


def test_a_held_k_is_capped_to_keep_the_fit_fast(hard_1khz, monkeypatch):
    t, z = hard_1khz
    monkeypatch.setattr(S, "HELD_STEPS", 2e4, raising=False)
    res = S.fit_trajectory(t, z, radius=0.1, mass=1.0, maxiter=2)
    assert res.k == pytest.approx((0.25 * 2e4 / (t[-1] - t[0])) ** 2)
    assert res.k < res.k_lower_bound and res.k_stderr == np.inf
    assert any("to keep the model within" in n for n in res.notes), res.notes


def test_a_hertz_record_is_fitted_in_the_laws_units():
    """Regression: the record fit (``diffpen fit --data --law hunt_crossley``) started from
    the linear closed forms in N/m and N s/m and used them as a Hunt-Crossley k (N/m^n) and
    c (N s/m^(n+1)), bounding c within 1e3 of that start: a Hertz ball's record (1 kg, n 1.5,
    k 1e6, c 3e4, 0.1 mm noise) ended at k 5.1e5, c 1.5e4 (c at its bound), the iteration
    limit reached. The start now takes the law's stiffness and damping at the depth the
    record's start energy allows (tuning.stable.law_k, law_c), and the fit recovers both
    within 0.5%."""
    import diffpen as dp
    law = dp.laws.hunt_crossley(1.5)
    t, z = S.synthetic_record(1e6, 3e4, law=law, duration=1.5, noise=1e-4, seed=5)
    res = S.fit_trajectory(t, z, radius=0.1, mass=1.0, law=law)
    assert res.k == pytest.approx(1e6, rel=5e-3) and res.c == pytest.approx(3e4, rel=5e-3)
    assert any("N/m^1.5" in n and "N s/m^2.5" in n for n in res.notes), res.notes
