"""The package's import structure, read from the source (no import needed): diffpen never
imports tuning, and tuning's modules import each name from the module that defines it, not
through ``tuning.fit``'s re-exports (importing the record readers loaded optax, the LM
driver and the whole fitting stack through them)."""
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
