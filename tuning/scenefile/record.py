"""The :class:`SceneFile` record (and its :class:`FitSpec`) a scene file reads into, and
the resolution of body references (index, name, ``group[i, j]``) against it."""
from __future__ import annotations

import dataclasses

import diffpen as dp

from .. import validate as V
from ..scenes import SceneSetup
from ..validate import Where
from .leaves import _default_params
from .schema import _NODE, _x64


# --------------------------------------------------------------------------- results
@dataclasses.dataclass
class FitSpec:
    """The validated ``[fit]`` table.

    free: parameter leaf paths to fit (dotted, see the module docstring); empty means the
      fitting code's default.  bounds: ``{path: (lo, hi)}``.  space: ``{path: "log" |
      "linear"}`` for every free path.  targets: bounce targets or None.  data: absolute
      record paths or None.  body, plane: indices.  observe: body names the records observe.
    first_state, flight_frames, horizon: record fits' start-state estimate (``"record"`` /
      ``"fit"``), its cap on flight frames, and the growing-horizon stages (s) before the
      whole records; None: the command line's or the built-in default.
    """
    free: list
    bounds: dict
    space: dict
    targets: dict | None
    data: list | None
    body: int
    plane: int
    observe: list
    method: str = "lm"
    maxiter: int | None = None
    lr: float = 0.05
    weights: dict | None = None
    settle_tol: float = 1e-3
    first_state: str | None = None
    flight_frames: int | None = None
    horizon: list | None = None


@dataclasses.dataclass
class SceneFile:
    """A parsed scene file (nothing compiled).

    path: the file.  setup: :class:`tuning.scenes.SceneSetup` (scene, dt, steps, k, c, law,
    metrics).  fit: the raw ``[fit]`` dict (validated) or None; spec: its :class:`FitSpec`.
    names: ``{name: body index}`` of named bodies and builder groups' nodes (``rope[3]``).
    planes: ``{name: plane index}``.  nodes: ``{builder name: index array}``.
    compile_options: keyword arguments for :func:`diffpen.compile` (integrator, law, ...).
    """
    path: str
    setup: SceneSetup
    fit: dict | None
    spec: FitSpec | None = None
    names: dict = dataclasses.field(default_factory=dict)
    planes: dict = dataclasses.field(default_factory=dict)
    nodes: dict = dataclasses.field(default_factory=dict)
    compile_options: dict = dataclasses.field(default_factory=dict)
    _sim: tuple | None = dataclasses.field(default=None, repr=False)

    @property
    def scene(self) -> dp.Scene:
        return self.setup.scene

    def body_index(self, ref) -> int:
        """Body index of ``ref`` (an index, a name or ``NAME[i,...]``); SceneFileError if none."""
        return _Refs(self).body(Where(self.path, "body"), ref)

    def compile(self, **overrides) -> dp.Simulator:
        """``diffpen.compile`` with the file's dt and options (``overrides`` win). Lazy: JAX
        compiles on the first rollout. Without overrides, the simulator built while checking
        ``[fit] params`` is reused (same scene, dt, options and dtype)."""
        if not overrides and self._sim is not None and self._sim[0] == _x64():
            return self._sim[1]
        kw = dict(self.compile_options)
        kw.update(overrides)
        dt = kw.pop("dt", self.setup.dt)
        return dp.compile(self.scene, dt, **kw)

    def params(self, sim: dp.Simulator) -> dp.Params:
        """``sim.params`` with the file's materials, falling back to the top-level k and c."""
        return _default_params(sim, self.setup.k, self.setup.c)


# --------------------------------------------------------------------------- references
class _Refs:
    def __init__(self, sf_or_names, nodes=None, n_bodies=None):
        if isinstance(sf_or_names, SceneFile):
            self.names, self.nodes = sf_or_names.names, sf_or_names.nodes
            self.n = sf_or_names.scene.n_bodies
        else:
            self.names, self.nodes, self.n = sf_or_names, nodes, n_bodies

    def body(self, w: Where, ref) -> int:
        if isinstance(ref, bool) or not isinstance(ref, (int, str)):
            raise w.error(f"must be a body index or name, got {V._kind(ref)} {V._show(ref)}.")
        if isinstance(ref, int):
            if not 0 <= ref < self.n:
                raise w.error(f"is body {ref}, but the scene has {self.n} bodies (0.."
                              f"{self.n - 1}) at this point; bodies are numbered spheres, "
                              "particles, boxes, rigid_spheres, then builder nodes.")
            return ref
        if ref in self.names:
            return self.names[ref]
        m = _NODE.match(ref.strip())
        if m and m.group(1) in self.nodes:
            idx = self.nodes[m.group(1)]
            ij = tuple(int(s) for s in m.group(2).split(","))
            if len(ij) != idx.ndim or not all(-s <= v < s for v, s in zip(ij, idx.shape)):
                raise w.error(f"{V._show(ref)} is outside {m.group(1)!r}, whose nodes have shape "
                              f"{idx.shape}: write {m.group(1)}[" + ",".join(
                                  f"0..{s - 1}" for s in idx.shape) + "].")
            return int(idx[ij])
        known = [n for n in self.names if "[" not in n][:8] + [f"{g}[...]" for g in self.nodes]
        raise w.error(f"names body {V._show(ref)}, which the scene does not have; known: "
                      f"{', '.join(known) or 'no named bodies'} (or an index 0.."
                      f"{self.n - 1}). Give the body a name = \"...\" first.")
