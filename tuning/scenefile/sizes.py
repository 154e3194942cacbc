"""Size guards of a scene file: steps, bodies, dense contact pairs and trajectory memory,
estimated from the tables and refused above the limits before anything is built."""
from __future__ import annotations

import math

from diffpen.checks import human_bytes, human_time

from .schema import BODY_TABLES, BUILDER_TABLES


class _SizeGuards:
    """Mixin of :class:`_Loader`: size estimates and guards."""

    # ---------------------------------------------------------------- sizes
    def _count(self, w, e, key, default=None):
        v = e.get(key, default)
        return v if isinstance(v, int) and not isinstance(v, bool) and v > 0 else 0

    def check_sizes(self, dt, duration, has_broadphase):
        """Refuse, from estimates and before building, scenes too large to run."""
        lim = self.limits
        n_direct = {k: len(self.doc[k]) if isinstance(self.doc.get(k), list) else 0
                    for k in BODY_TABLES}
        n_nodes = 0
        for key in BUILDER_TABLES:
            for e in (self.doc.get(key) if isinstance(self.doc.get(key), list) else []):
                if not isinstance(e, dict):
                    continue
                if key in ("ropes", "crumple_bars"):
                    n = self._count(None, e, "n")
                    n_nodes += n * (2 if key == "crumple_bars" and "width" in e else 1)
                else:
                    dims = ("nx", "ny") if key == "cloths" else ("nx", "ny", "nz")
                    n_nodes += math.prod(self._count(None, e, d) for d in dims)
        n_bodies = sum(n_direct.values()) + n_nodes
        if n_bodies > lim["max_bodies"]:
            raise self.root.error(
                f"describes {n_bodies:,} bodies ({n_nodes:,} of them builder nodes); the limit "
                f"is {lim['max_bodies']:,} (building and compiling such a scene takes minutes "
                "and GiB). Make it smaller (in Python, load_scene_file(..., max_bodies=) reads "
                "it; the diffpen commands keep the limit).")
        spheres = [e for k in ("spheres", "rigid_spheres") for e in
                   (self.doc.get(k) if isinstance(self.doc.get(k), list) else [])
                   if isinstance(e, dict) and e.get("collide", True) is not False]
        boxes = [e for e in (self.doc.get("boxes") if isinstance(self.doc.get("boxes"), list)
                             else []) if isinstance(e, dict) and e.get("collide", True)
                 is not False]
        ns, nb = len(spheres), len(boxes)
        pairs = ns * (ns - 1) // 2 + ns * nb
        if not has_broadphase and pairs > lim["max_dense_pairs"]:
            mem = pairs * (3 * 4 + 12 * 8) / 2**30
            build = pairs * 1e-6
            raise self.root.error(
                f"has {ns:,} colliding spheres and {nb:,} boxes: {pairs:,} contact pairs "
                f"evaluated every step without a broad phase (about {mem:.1f} GiB of pair "
                f"arrays per step and {human_time(build)} to list them before compiling); the "
                f"limit is {lim['max_dense_pairs']:,}. Add broadphase = {{ kind = \"grid\" }} "
                "(or { kind = \"aabb\", max_pairs = ... }) at the top level (in Python, "
                "load_scene_file(..., max_dense_pairs=) reads it as it is; the diffpen commands "
                "keep the limit).")
        steps = duration / dt
        per_body = 13 if (n_direct["boxes"] or n_direct["rigid_spheres"]) else 6
        traj = steps * max(n_bodies, 1) * per_body * 8
        seconds = steps * max(1e-6, 2e-8 * (n_bodies + (pairs if not has_broadphase else
                                                         8 * n_bodies)))
        if steps > lim["max_steps"] or traj > lim["max_trajectory_bytes"]:
            raise self.w("duration").error(
                f"= {duration:g} s at dt = {dt:g} s is {steps:.3g} steps: a rollout saving "
                f"every step would hold about {human_bytes(traj)} and run for roughly "
                f"{human_time(seconds)}. The limits are {lim['max_steps']:,} steps and "
                f"{human_bytes(lim['max_trajectory_bytes'])}; shorten duration or raise dt (in "
                "Python, load_scene_file(..., max_steps=, max_trajectory_bytes=) reads it; the "
                "diffpen commands keep the limit).")

