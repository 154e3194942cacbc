"""The package's import structure, read from the source (no import needed): diffpen never
imports tuning, and tuning's modules import each name from the module that defines it, not
through ``tuning.fit``'s re-exports (importing the record readers loaded optax, the LM
driver and the whole fitting stack through them); and, imported, every name the packages
export resolves and the figure functions return what they wrote."""
import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
FIT_REEXPORTS = {"FitError", "Progress", "default_optimizer", "default_bounds", "safe_bounds",
                 "residual_reached", "RESIDUAL_FACTOR"}


def _imports(package: str):
    """``(file, line, module, names)`` of every import statement under ``package``, function
    level ones included; ``module`` resolved to its dotted name."""
    for path in sorted((ROOT / package).rglob("*.py")):
        pkg = list(path.relative_to(ROOT).parent.parts)     # the module's package
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                for a in node.names:
                    yield path, node.lineno, a.name, set()
            elif isinstance(node, ast.ImportFrom):
                base = pkg[:len(pkg) - node.level + 1] if node.level else []
                module = ".".join(base + ([node.module] if node.module else []))
                yield path, node.lineno, module, {a.name for a in node.names}


def test_diffpen_never_imports_tuning():
    bad = [f"{p.relative_to(ROOT)}:{line}" for p, line, module, _ in _imports("diffpen")
           if module == "tuning" or module.startswith("tuning.")]
    assert not bad, bad


def test_tuning_imports_names_from_their_defining_modules():
    bad = [f"{p.relative_to(ROOT)}:{line} imports {sorted(names & FIT_REEXPORTS)} from "
           "tuning.fit" for p, line, module, names in _imports("tuning")
           if module == "tuning.fit" and names & FIT_REEXPORTS]
    assert not bad, bad


def test_every_exported_name_resolves():
    """Regression: ``diffpen.__all__`` still named the ``plastic`` module after it was removed,
    so ``from diffpen import *`` raised AttributeError. Every name of ``diffpen.__all__`` and
    ``tuning.__all__`` resolves."""
    import diffpen
    import tuning
    for package in (diffpen, tuning):
        missing = [n for n in package.__all__ if not hasattr(package, n)]
        assert not missing, (package.__name__, missing)
    namespace = {}
    exec("from diffpen import *", namespace)
    assert "Scene" in namespace and "terms" in namespace


def test_figure_functions_return_the_paths_they_wrote(tmp_path):
    """Regression: the README says tuning.plots returns the paths it writes; fit_figure,
    trajectory_fit_figure and heatmap returned None."""
    import numpy as np
    from tuning import plots
    t = np.linspace(0.0, 1.0, 20)
    z = np.abs(np.sin(6.0 * t))
    paths = [
        plots.fit_figure(tmp_path / "fit.png", t, z, targets={"apex1": 0.5},
                         achieved={"apex1": 0.49}, loss_history=[1.0, 0.1], radius=0.1),
        plots.trajectory_fit_figure(tmp_path / "traj.png", t, z, z * 0.9, [1.0, 0.5]),
        plots.heatmap(tmp_path / "map.png", np.geomspace(1e3, 1e4, 3),
                      np.geomspace(1.0, 10.0, 4), np.ones((3, 4)), metric="apex1")]
    for name, path in zip(("fit.png", "traj.png", "map.png"), paths):
        assert path == tmp_path / name and path.stat().st_size > 0


def _constant_arm_conditions(tree):
    """``(line, source)`` of every assert that holds a condition ``A if C else K`` (or ``K if C
    else A``) whose one arm is a check (a comparison, a call such as ``np.allclose(...)``, an
    ``and``/``or``) and the other a constant (a number, a negative
    one, True...), anywhere in the assert (inside ``and``/``or``, ``np.all(...)``): Python
    reads ``assert x < a if c else b`` as ``(x < a) if c else b``, and the constant arm makes
    the check always pass (or always fail) on that branch. A bound held in a name (``else
    tol``) is not seen."""
    def constant(node):
        return isinstance(node, ast.Constant) or (isinstance(node, ast.UnaryOp)
                                                  and isinstance(node.operand, ast.Constant))
    for node in ast.walk(tree):
        if not isinstance(node, ast.Assert):
            continue
        for t in ast.walk(node.test):
            if isinstance(t, ast.IfExp) and any(
                    isinstance(a, (ast.Compare, ast.Call, ast.BoolOp)) and constant(b)
                    for a, b in ((t.body, t.orelse), (t.orelse, t.body))):
                yield node.lineno, ast.unparse(node.test)
                break


def test_no_assert_checks_only_one_branch_of_a_condition():
    """Regression: tests/test_event_gradients.py asserted ``np.all(err < 0.025 if linear
    else 0.06)``, always true for no_tension's contact durations (parenthesise the bound)."""
    bad = [f"{p.relative_to(ROOT)}:{line}: {src}"
           for p in sorted((ROOT / "tests").glob("*.py"))
           for line, src in _constant_arm_conditions(ast.parse(p.read_text(), str(p)))]
    assert not bad, bad
    # the pattern is found where it occurs, in each of its forms
    for old in ("assert np.all(_err(d, r) < 0.025 if law == 'linear' else 0.06)",
                "assert 0.06 if law == 'linear' else err < 0.025",
                "assert ok and (err < 0.025 if linear else -1)",
                "assert np.allclose(a, b) if exact else True"):
        assert list(_constant_arm_conditions(ast.parse(old))), old
    assert not list(_constant_arm_conditions(ast.parse("assert x < (1 if c else 2)")))
