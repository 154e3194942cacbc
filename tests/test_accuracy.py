"""tuning.reports.accuracy: the work-precision ladder converges at each integrator's order,
recommend picks the cheapest point meeting a tolerance, and the plot is written."""
import math

import pytest

from tuning.reports.accuracy import accuracy, plot_accuracy, recommend


@pytest.fixture(scope="module")
def small_accuracy():
    return accuracy(integrators=("semi_implicit_euler", "rk4"), dts=(2e-3, 2.5e-4),
                    widths=(0.0, 1e-2), width_dt=5e-4, repeats=2,
                    problems=("ball", "spring"), default_dtypes=("float32",))


def test_work_precision_errors_converge_at_the_integrators_order(small_accuracy):
    sp = small_accuracy["problems"]["spring"]
    for integ, order in (("semi_implicit_euler", 1), ("rk4", 4)):
        e1, e2 = sp[integ][0]["error"], sp[integ][1]["error"]
        assert math.log2(e1 / e2) / 3 == pytest.approx(order, abs=0.3)     # dt / 8
        assert all(p["time"] > 0 for p in sp[integ])
    ball = small_accuracy["problems"]["ball"]
    # hard contact: the damping switches on with a jump at d = 0, so every integrator is
    # limited to about first order there (and the onset phase makes it non-monotone at coarse
    # dt); over a factor 8 in dt the error still drops
    for integ in ("semi_implicit_euler", "rk4"):
        e1, e2 = ball[integ][0]["error"], ball[integ][1]["error"]
        assert e2 < 0.7 * e1 and e1 < 0.05
    # a wide smoothing band moves the apexes more than the exact ramp at the same dt
    w = small_accuracy["widths"]
    assert w[1]["error"] > w[0]["error"]
    d, = small_accuracy["default"]
    assert d["dtype"] == "float32" and d["error"] < 0.05 and d["time"] > 0


def test_recommend_picks_the_cheapest_point_meeting_tol(small_accuracy):
    pts = [dict(p, integrator=i) for i, ps in small_accuracy["problems"]["ball"].items()
           for p in ps]
    tol = sorted(p["error"] for p in pts)[len(pts) // 2]
    rec = recommend(small_accuracy, tol)
    ok = [p for p in pts if p["error"] <= tol]
    assert rec["time"] == min(p["time"] for p in ok) and rec["error"] <= tol
    assert recommend(small_accuracy, 1e-300) is None


def test_plot_writes_a_png(small_accuracy, tmp_path):
    pytest.importorskip("matplotlib")
    path = tmp_path / "wp.png"
    plot_accuracy(small_accuracy, str(path))
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
