"""tuning.reports.gradient_check: the gradient report against the derivative of the continuous
hard-contact model (the event-gradient table is tested in test_event_gradients.py)."""
from tuning.reports.gradient_check import gradient_report


def test_gradient_report_against_the_continuous_derivative():
    rows = gradient_report(dts=(2.5e-4,), widths=(1e-2,), rel_steps=(1e-2, 1e-3, 1e-4, 1e-5))
    by = {(r["quantity"], r["param"]): r for r in rows}
    apex_k, apex_c = by[("apex", "k")], by[("apex", "c")]
    # smoothed contact at a small step: d apex / dk and d apex / dc within 5% of the
    # derivative of the continuous hard-contact model, and FD agrees up to large steps
    assert apex_k["grad_rel_error"] < 0.05 and apex_c["grad_rel_error"] < 0.05
    assert apex_k["largest_agreeing_rel_step"] is not None
    assert apex_c["largest_agreeing_rel_step"] >= 1e-3
