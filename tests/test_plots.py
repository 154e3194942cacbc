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

