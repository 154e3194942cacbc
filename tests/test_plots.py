"""tuning.plots draws and returns the paths it wrote; it prints nothing (the command line and the
examples print)."""
import pytest

from tuning import plots

pytest.importorskip("matplotlib")


def test_save_strip_and_figure_return_the_path_and_print_nothing(tmp_path, capsys):
    def draw(ax, i):
        ax.plot([0.0, 1.0], [0.0, float(i)])
    out = plots.save_strip(draw, [1, 2], tmp_path / "strip.png", title="strip")
    assert out == tmp_path / "strip.png" and out.stat().st_size > 0
    plt = plots.require_matplotlib()
    fig, ax = plt.subplots()
    ax.plot([0.0, 1.0])
    out = plots.save_figure(fig, str(tmp_path / "fig.png"))
    assert out == tmp_path / "fig.png" and out.stat().st_size > 0
    assert capsys.readouterr() == ("", "")



def test_heatmap_cells_are_centred_on_log_axes():
    """pcolormesh's "nearest" shading put the cell edges at arithmetic midpoints: on log
    axes the cells of a geomspace grid had unequal widths and the first a negative edge
    (-821 for k 1e3..1e5). The edges are geometric midpoints now, every cell one width."""
    import numpy as np
    e = plots.cell_edges(np.geomspace(1e3, 1e5, 3), True)
    np.testing.assert_allclose(e, [10 ** 2.5, 10 ** 3.5, 10 ** 4.5, 10 ** 5.5], rtol=1e-12)
    np.testing.assert_allclose(plots.cell_edges([0.0, 1.0, 3.0], False), [-0.5, 0.5, 2, 4])


def test_a_sweep_target_outside_the_grid_says_no_contour_is_drawn(capsys):
    """--target outside the metric's range drew no contour and said nothing."""
    from types import SimpleNamespace

    from tuning.cli.sweep import _target_drawn
    args = SimpleNamespace(target=5.0, plot="h.png", metric="apex_heights")
    assert _target_drawn(args, [[0.1, 0.9], [float("nan"), 0.5]]) is False
    assert "outside the grid's apex_heights (0.1 .. 0.9): no contour" in capsys.readouterr().err
    args.target = 0.3
    assert _target_drawn(args, [[0.1, 0.9]]) is True and capsys.readouterr().err == ""
    args.plot = None
    assert _target_drawn(args, [[0.1, 0.9]]) is None


def test_the_cloth_sag_example_checks_its_picture_path_before_computing(tmp_path,
                                                                        monkeypatch):
    """Regression: examples/fit_cloth_sag.py took any --out and created its folder after
    the fit (by default ./examples/images under the current folder, wherever it ran); now
    --out is checked first, as in the other examples."""
    import os
    import sys
    here = os.path.join(os.path.dirname(__file__), "..", "examples")
    monkeypatch.syspath_prepend(here)
    monkeypatch.chdir(tmp_path)
    sys.modules.pop("fit_cloth_sag", None)
    import fit_cloth_sag
    with pytest.raises(SystemExit) as e:
        fit_cloth_sag.main(["--out", str(tmp_path / "missing" / "x.png")])
    assert e.value.code == 2 and os.listdir(tmp_path) == []
