"""Built-in scenes for the command line and the examples.

``SCENES`` maps a name to a builder ``builder(**options) -> SceneSetup``. A builder takes only
keyword options (each with a default) and returns the scene plus what the command line needs to
run and report it. Add a scene by adding an entry::

    SCENES["chain"] = chain      # def chain(**options) -> SceneSetup
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

import diffpen as dp
from diffpen import SceneError

__all__ = ["SceneSetup", "SCENES", "ball_scene", "ball", "chain", "cloth", "get_scene"]


@dataclasses.dataclass
class SceneSetup:
    """A ready-to-compile scene with its run settings.

    scene: the :class:`diffpen.Scene`.
    dt: time step, s.  steps: default rollout length (steps).
    k, c: default contact stiffness (N/m) and damping (N s/m) for every material.
    law: contact law name.  body: the body whose metrics are reported (None: none).
    metrics: ``metrics(sim, traj, params) -> dict`` of plain numbers/lists (None: the
      command line reports only the final state).
    description: one line for ``--help`` and printouts.
    compile_options: further keyword arguments of :func:`diffpen.compile` (integrator,
      smoothing, substeps, broadphase, exponent), e.g. from a scene file.
    """
    scene: dp.Scene
    dt: float
    steps: int
    k: float
    c: float
    law: str = "linear"
    body: int | None = 0
    metrics: Callable | None = None
    description: str = ""
    compile_options: dict = dataclasses.field(default_factory=dict)


def _ball_metrics(settle_tol: float, n_apex: int):
    def metrics(sim, traj, params):
        from .metrics import ball_metrics_dict
        return ball_metrics_dict(sim, traj, params, body=0, n_apex=n_apex,
                                 settle_tol=settle_tol)
    return metrics


def ball_scene(*, radius: float = 0.1, mass: float = 1.0, height: float = 1.0,
               velocity: float = 0.0, gravity: float = 9.81) -> dp.Scene:
    """The bouncing ball: one sphere above the ground plane z = 0 (normal +z, offset 0, default
    material). The one builder of this scene: the built-in ``ball``, ``diffpen fit`` and
    ``diffpen sweep``, system identification and the trust reports all use it.

    Args:
      radius: m.  mass: kg.  height: initial centre height, m.
      velocity: initial vertical velocity, m/s (positive up).
      gravity: m/s^2, pointing down (-z); 0 leaves gravity out.
    """
    scene = dp.Scene(gravity=(0.0, 0.0, -float(gravity) if gravity else 0.0))
    scene.add_sphere(radius=radius, mass=mass, position=(0.0, 0.0, height),
                     velocity=(0.0, 0.0, velocity))
    scene.add_plane()
    return scene


def _timing(dt, duration) -> None:
    """A built-in scene's ``dt`` and ``duration`` (s): finite numbers > 0 (a ZeroDivisionError
    before)."""
    for name, v in (("dt", dt), ("duration", duration)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(v) and v > 0.0):
            raise SceneError(f"{name} must be a finite number of seconds > 0, got {v!r}.")


def ball(*, radius: float = 0.1, mass: float = 1.0, drop: float = 1.0, k: float = 1e4,
         c: float = 20.0, dt: float = 1e-3, duration: float = 3.0, gravity: float = 9.81,
         settle_tol: float = 1e-3, n_apex: int = 3, law: str = "linear") -> SceneSetup:
    """A sphere dropped from rest onto the ground plane z = 0.

    Args:
      radius: m.  mass: kg.  drop: initial CENTRE height, m (must exceed ``radius``).
      k: N/m.  c: N s/m.  dt: s.  duration: rollout length, s.  gravity: m/s^2 (downwards).
      settle_tol: settling band for the reported settling time, m.
      n_apex: number of bounce apexes reported.
    """
    if not drop > radius:
        raise dp.SceneError(f"the ball's centre must start above its radius: drop={drop} m "
                            f"<= radius={radius} m would start in contact. Raise --drop.")
    _timing(dt, duration)
    scene = ball_scene(radius=radius, mass=mass, height=drop, gravity=gravity)
    steps = max(1, int(round(duration / dt)))
    return SceneSetup(scene=scene, dt=dt, steps=steps, k=k, c=c, law=law, body=0,
                      metrics=_ball_metrics(settle_tol, n_apex),
                      description=f"ball r={radius} m, m={mass} kg dropped from z={drop} m "
                                  "onto the plane z=0")


def chain(*, seed: int = 0, dt: float = 0.1, duration: float = 200.0, k: float = 0.0,
          c: float = 0.0) -> SceneSetup:
    """The workshop paper's ball-spring chain (``diffpen.builders.paper_chain``): 7 balls of
    10 kg, ends fixed at (100, 0, 100) and (500, 0, 100), zero-rest springs KS = 50 N/m, drag
    KD = 1 N s/m per ball, g = 9.8 m/s^2, DT = 0.1 s, free balls scattered with ``seed``.

    Metrics: ``final_positions`` ((7, 3) list, m), the directly solved static ``equilibrium``
    and ``max_error_vs_equilibrium`` (m). ``k``/``c`` (contact) are unused: no contacts.
    """
    from diffpen.builders import paper_chain, paper_chain_equilibrium
    _timing(dt, duration)
    scene, balls = paper_chain(seed=seed)

    def metrics(sim, traj, params):
        import numpy as np
        final = np.asarray(traj.position)[-1]
        eq = paper_chain_equilibrium()
        return {"final_positions": final.tolist(), "equilibrium": eq.tolist(),
                "max_error_vs_equilibrium": float(np.abs(final - eq).max())}
    return SceneSetup(scene=scene, dt=dt, steps=max(1, int(round(duration / dt))), k=k, c=c,
                      body=None, metrics=metrics,
                      description="the paper's 7-ball chain (KS=50, KD=1, MASS=10, DT=0.1)")


def cloth(*, n: int = 9, size: float = 0.4, mass: float = 0.25, structural: float = 20.0,
          dt: float = 1.5e-3, duration: float = 3.0, k: float = 0.0,
          c: float = 0.0) -> SceneSetup:
    """A square cloth (``diffpen.builders.add_cloth``) of ``n`` x ``n`` nodes, ``size`` m wide,
    ``mass`` kg, pinned at its four corners, sagging under gravity (structural k =
    ``structural`` N/m, shear 10 N/m, bend 2 N/m, drag 0.05 N s/m per node).

    Metrics: ``centre_sag`` (m, depth of the centre node below the corners at the end),
    ``max_speed`` (m/s, fastest node at the end: ~0 once settled). ``k``/``c`` are unused.
    """
    from diffpen.builders import add_cloth
    _timing(dt, duration)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 3:
        raise SceneError(f"cloth n must be a whole number of nodes >= 3 (a centre node between "
                         f"pinned corners), got {n!r}.")
    scene = dp.Scene(gravity=(0.0, 0.0, -9.81))
    nodes = add_cloth(scene, n, n, size / (n - 1), mass=mass, structural=(structural, 0.05),
                      shear=(10.0, 0.02), bend=(2.0, 0.0), drag=0.05,
                      pinned=[(0, 0), (0, -1), (-1, 0), (-1, -1)])
    centre = int(nodes[n // 2, n // 2])

    def metrics(sim, traj, params):
        import numpy as np
        x, v = np.asarray(traj.position)[-1], np.asarray(traj.velocity)[-1]
        return {"centre_sag": float(-x[centre, 2]),
                "max_speed": float(np.linalg.norm(v, axis=-1).max())}
    return SceneSetup(scene=scene, dt=dt, steps=max(1, int(round(duration / dt))), k=k, c=c,
                      body=None, metrics=metrics,
                      description=f"{n}x{n} cloth, {size} m, pinned at its corners, sagging")


#: Built-in scenes by name: ``builder(**options) -> SceneSetup``.
SCENES: dict[str, Callable[..., SceneSetup]] = {
    "ball": ball,
    "chain": chain,
    "cloth": cloth,
}


def get_scene(name: str, **options) -> SceneSetup:
    """Build the built-in scene ``name`` with keyword ``options``."""
    if name not in SCENES:
        raise KeyError(f"unknown scene {name!r}; built-in scenes: {sorted(SCENES)} (or give "
                       "a .toml scene file).")
    return SCENES[name](**options)
