"""TOML scene files: every element of a :class:`diffpen.Scene`, the run settings, and what to
fit, so that ``diffpen fit myscene.toml`` / ``diffpen simulate myscene.toml`` need no Python.

The schema (SI units; every table is optional except one body; unknown keys are errors)::

    description = "..."             # one line for printouts
    gravity = [0.0, 0.0, -9.81]     # m/s^2
    dt = 1e-3                       # s
    duration = 3.0                  # s, default rollout length (>= dt)
    law = "linear"                  # "linear", "no_tension", "hunt_crossley"
    exponent = 1.5                  # Hunt-Crossley exponent (>= 1); law = "hunt_crossley" only
    integrator = "semi_implicit_euler"   # any of diffpen.integrators.INTEGRATORS
    smoothing = "auto"              # contact smoothing width, m (>= 0) or "auto"
    substeps = 1                    # int >= 1 or "auto"
    plastic_smoothing = 1e-3        # strain width of the plastic yield onset
    broadphase = { kind = "grid" }  # or { kind = "aabb", max_pairs = 4096 }; also margin,
                                    # cell_size, max_per_cell, bounds = [[x0,y0,z0],[x1,y1,z1]]
    k = 1e4                         # contact k (N/m) and c (N s/m) of every material that
    c = 20.0                        #   does not give its own (defaults 1e4 and 20.0)
    allow_overlap = false           # bodies may start overlapping (also per body, plane and
                                    #   fixed sphere), where the library checks overlaps

    [materials.rubber]              # contact material ("default" exists already)
    k = 1e4                         # N/m
    c = 20.0                        # N s/m
    friction = 0.3                  # Coulomb mu >= 0 (box corners, rigid spheres)
    slip_speed = 0.01               # m/s > 0

    [[spheres]]                     # radius, mass, position; optional name, velocity,
    [[particles]]                   #   material, pinned, collide (particles: no radius)
    [[boxes]]                       # half_extents, mass, position; optional name, velocity,
    [[rigid_spheres]]               #   orientation [w,x,y,z], angular_velocity (world frame)
                                    #   OR body_angular_velocity (body frame), inertia [3]
                                    #   (kg m^2), material, pinned, collide
    [[planes]]                      # normal [0,0,1], offset 0, material, name (a named plane's
                                    #   offset is the param extra.plane_offset.NAME when the
                                    #   library supports it)
    [[fixed_spheres]]               # center, radius, material
    [spring_groups.NAME]            # k, c: declare a spring group
    [[springs]]                     # a, b (body index or name; b may be a world point
                                    #   [x,y,z]), k, c, rest_length, group
    [[anchored_springs]]            # a, b (omit b for a world point), anchor_a, anchor_b
                                    #   (body frame, m), k, c, rest_length, group
    [[plastic_springs]]             # a, b, k, c, yield_strain in (0, 1), rest_length, group
    [[drag]]                        # bodies (a ref or array of refs; a builder's name means
                                    #   all its nodes), c (N s/m), group
    [[ropes]]                       # n, start, end, mass, k; c, name ("rope"), pinned [0],
                                    #   bend (k | [k, c] | false), drag, velocity, collide
    [[cloths]]                      # nx, ny, spacing, mass; name ("cloth"), origin, axes,
                                    #   structural, shear, bend, pinned [[i,j],...], drag, ...
    [[jellies]]                     # nx, ny, nz, spacing, mass; name ("jelly"), origin, edge,
                                    #   face, body, pinned [[i,j,l],...], drag, velocity, ...
    [[crumple_bars]]                # n, start, end, mass, k; c, yield_strain, name ("bar"),
                                    #   width, pinned, drag, velocity, collide

    [fit]
    params = ["contact.rubber.k", "contact.rubber.c"]   # leaf paths of sim.params()
    body = 0                        # index or name (bounce fits: the bouncing body)
    plane = 0                       # index or name
    settle_tol = 1e-3               # m
    method = "lm"                   # "lm", "adam", "sgd";  lr = 0.05 (optax)
    maxiter = 40                    # targets: the whole fit (default 40 lm, 400 optax);
                                    #   records: per horizon stage (default 30; t,z 15)
    observe = ["cube"]              # bodies the records observe (default: the named bodies)
    first_state = "fit"             # record fits: "record" (row 0), "fit" (parabola) or
                                    #   "refine" (row 0, refined with the parameters);
    flight_frames = 20              #   its cap on flight frames (default: the first flight);
    horizon = [0.5, 1.0]            #   growing-horizon stages, s, before the whole records
                                    #   (default 1/8, 1/4, 1/2 of the longest; [] none)
    [fit.bounds]                    # "path" = [lo, hi]
    [fit.space]                     # "path" = "log" | "linear" (default: linear for offsets
                                    #   and other signed leaves, log for positive ones)
    [fit.weights]                   # target or loss-term name = weight >= 0
    [fit.targets]                   # apex_heights, settling_time, contact_durations,
                                    #   restitution, max_penetration
    # data = "record.csv"           # or an array of records, instead of targets

Bodies are numbered: spheres, particles, boxes, rigid_spheres, then the nodes of ropes,
cloths, jellies and crumple_bars, each in file order. A body is referred to by its index, by
its ``name``, or, for a builder's node, as ``NAME[i]`` / ``NAME[i,j]`` / ``NAME[i,j,l]``
(negative indices count from the end). Parameter paths are the ``jax.tree_util`` key paths of
``sim.params()`` written with dots (``contact.rubber.k``, ``springs.rope.stretch.c``,
``extra.friction.rubber``, ``extra.drag.rope.drag``, ``extra.plastic.bar``) or as
``jax.tree_util.keystr`` gives them (``.contact['rubber'].k``).

Every value is checked when the file is read -- types without coercion (``radius = "0.1"``
and ``mass = true`` are errors), ranges, references, sizes (steps, bodies, contact pairs:
estimated and refused above limits the caller can raise) -- with the file name, the key and
the fix in the message, before anything is compiled.
"""
from __future__ import annotations

from ..validate import SceneFileError
from .fitting import fit_file
from .leaves import leaf_space, param_leaves
from .loader import load_scene_file
from .record import FitSpec, SceneFile
from .schema import (MAX_BODIES, MAX_DENSE_PAIRS, MAX_STEPS, MAX_TRAJECTORY_BYTES,
                     is_scene_path)

__all__ = ["load_scene_file", "SceneFile", "FitSpec", "fit_file", "SceneFileError",
           "is_scene_path", "param_leaves", "leaf_space", "MAX_STEPS", "MAX_BODIES",
           "MAX_DENSE_PAIRS", "MAX_TRAJECTORY_BYTES"]
