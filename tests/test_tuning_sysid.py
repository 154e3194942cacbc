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


def test_recovers_k_and_c_with_covering_standard_errors(record):
    t, z = record
    res = S.fit_trajectory(t, z, radius=0.1, mass=1.0)
    assert abs(res.k / K_TRUE - 1) < 0.02 and abs(res.c / C_TRUE - 1) < 0.02
    # the reported standard errors cover the truth (95 % interval)
    assert abs(res.k - K_TRUE) <= 2.0 * res.k_stderr, (res.k, res.k_stderr)
    assert abs(res.c - C_TRUE) <= 2.0 * res.c_stderr, (res.c, res.c_stderr)
    assert 0 < res.k_stderr < 0.01 * K_TRUE and 0 < res.c_stderr < 0.01 * C_TRUE
    # the residual is the noise: the model (and its dt) explains the record
    assert res.rms == pytest.approx(1e-3, rel=0.1)
    assert res.dt_error < res.noise / 6
    assert len(res.horizons) >= 2          # grown bounce by bounce


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
