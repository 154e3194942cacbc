"""The ``[fit]`` table of a scene file: targets, records, method, and the params leaves to
fit with their bounds and search space."""
from __future__ import annotations

import numpy as np

import diffpen as dp

from .. import validate as V
from .leaves import _default_params, _keystr_paths, leaf_space, param_leaves, signed_leaf
from .record import FitSpec, SceneFile
from .schema import FIT, TARGETS, _x64


class _FitTable:
    """Mixin of :class:`_Loader`: the ``[fit]`` table."""

    # ---------------------------------------------------------------- [fit]
    def fit(self, sf: SceneFile, k, c) -> FitSpec:
        w = self.w("fit")
        fit = V.table(w, self.doc["fit"], example='[fit] params = ["contact.default.k"]')
        V.check_keys(w, fit, FIT)
        refs = self.refs()
        body = refs.body(w / "body", fit.get("body", 0))
        plane = 0
        if "plane" in fit:
            p = fit["plane"]
            if isinstance(p, str) and p in self.plane_names:
                plane = self.plane_names[p]
            elif isinstance(p, str):
                raise (w / "plane").error(
                    f"names plane {p!r}, which the scene does not have; named planes: "
                    f"{sorted(self.plane_names) or 'none'} (or give a plane index).")
            else:
                plane = V.integer(w / "plane", p, low=0)
                if plane >= len(self.scene.planes):
                    raise (w / "plane").error(f"is plane {plane}, but the scene has "
                                              f"{len(self.scene.planes)} plane(s).")
        has_t, has_d = "targets" in fit, "data" in fit
        if has_t and has_d:
            raise w.error("has both [fit.targets] and data: give either targets (a bounce fit) "
                          "or data = \"record.csv\" (an array for several records), not both.")
        if not (has_t or has_d or fit.get("params")):
            raise w.error("says nothing to fit: add a [fit.targets] table, data = "
                          "\"record.csv\", or params = [...] (with records given on the "
                          "command line, diffpen fit SCENE.toml --data FILE.csv ...).")
        targets = None
        if has_t:
            targets = self.targets(w / "targets", fit["targets"])
        data = V.path_list(w / "data", fit["data"], suffix=".csv") if has_d else None
        observe = [n for n in self.names if "[" not in n]      # the named bodies
        if "observe" in fit:
            o = fit["observe"]
            items = o if isinstance(o, list) else [o]
            if not items:
                raise (w / "observe").error("is empty: name the observed bodies.")
            observe = []
            for j, x in enumerate(items):
                wj = w / "observe" / j if isinstance(o, list) else w / "observe"
                V.string(wj, x)
                if refs.body(wj, x) in [refs.body(wj, y) for y in observe]:
                    raise wj.error(f"names {x!r} a second time (or another name of the same "
                                   "body): list each observed body once.")
                observe.append(x)
        if fit.get("method") == "optax":    # the Python API's name: say what a file takes
            raise (w / "method").error("'optax' is tuning.fit's name for any optax optimiser; "
                                       "a scene file names it: \"adam\" or \"sgd\" (with "
                                       "lr), or \"lm\".")
        method = V.choice(w / "method", fit.get("method", "lm"), ["lm", "adam", "sgd"])
        maxiter = (V.integer(w / "maxiter", fit["maxiter"], low=1) if "maxiter" in fit
                   else None)
        lr = V.number(w / "lr", fit.get("lr", 0.05), low=0.0, low_open=True)
        settle = V.number(w / "settle_tol", fit.get("settle_tol", 1e-3), low=0.0,
                          low_open=True, unit="m")
        weights = None
        if "weights" in fit:
            ww = w / "weights"
            weights = {kk: V.number(ww / kk, v, low=0.0)
                       for kk, v in V.table(ww, fit["weights"],
                                            example="[fit.weights] settling_time = 2").items()}
            if targets is not None:
                bad = [kk for kk in weights if kk not in targets]
                if bad:
                    raise (ww / bad[0]).error(f"weights a target that is not given; targets: "
                                              f"{', '.join(targets)}.")
        first = (V.choice(w / "first_state", fit["first_state"],
                          ["record", "fit", "refine"])
                 if "first_state" in fit else None)
        frames = (V.integer(w / "flight_frames", fit["flight_frames"], low=3)
                  if "flight_frames" in fit else None)
        # [] says "the whole records only" (absent: the built-in growing horizon)
        horizon = (None if "horizon" not in fit else [] if fit["horizon"] == [] else
                   sorted(V.number_list(w / "horizon", fit["horizon"], low=0.0, low_open=True,
                                        unit="s")))
        # settings a fit of this kind does not read were accepted and ignored
        if "lr" in fit and method == "lm":
            raise (w / "lr").error("is the learning rate of the optax optimisers (method = "
                                   "\"adam\" or \"sgd\"); method = \"lm\" does not read it: "
                                   "drop it or choose an optax method.")
        if has_t:
            for key in ("first_state", "flight_frames", "horizon"):
                if key in fit:
                    raise (w / key).error("is read by fits to motion records (data = ...); a "
                                          "fit to [fit.targets] does not read it: drop it.")
        if fit.get("params") == []:
            raise (w / "params").error("is empty: name the leaves to fit (e.g. "
                                       "[\"contact.default.k\", \"contact.default.c\"]), or "
                                       "leave params out to fit the contact's k and c.")
        free, bounds, space = self.fit_params(w, fit, sf, k, c)
        return FitSpec(free=free, bounds=bounds, space=space, targets=targets, data=data,
                       body=body, plane=plane, observe=observe, method=method,
                       maxiter=maxiter, lr=lr, weights=weights, settle_tol=settle,
                       first_state=first, flight_frames=frames, horizon=horizon)

    def targets(self, w, t):
        V.table(w, t, example="[fit.targets] apex_heights = [0.4]")
        if not t:
            raise w.error(f"is empty: give at least one of {', '.join(sorted(TARGETS))}.")
        V.check_keys(w, t, TARGETS)
        out = {}
        for key, v in t.items():
            if key in ("apex_heights", "contact_durations"):
                out[key] = V.number_list(w / key, v, low=0.0, low_open=True,
                                         unit="m" if key == "apex_heights" else "s")
            elif key == "restitution":
                out[key] = V.number_list(w / key, v, low=0.0, low_open=True, high=1.0)
            else:
                out[key] = V.number(w / key, v, low=0.0, low_open=True,
                                    unit="m" if key == "max_penetration" else "s")
        return out

    def fit_params(self, w, fit, sf, k, c):
        """Free leaf paths, checked against the key paths of the compiled params pytree."""
        names = fit.get("params", [])
        if isinstance(names, str):
            names = [names]
        if not isinstance(names, list) or not all(isinstance(p, str) and p for p in names):
            raise (w / "params").error(f"must be an array of parameter paths (strings such as "
                                       f"\"contact.default.k\"), got {V._show(fit.get('params'))}.")
        for key in ("bounds", "space"):
            if key in fit:
                V.table(w / key, fit[key], example=f'[fit.{key}] "contact.default.k" = ...')
        if not names and not fit.get("bounds") and not fit.get("space"):
            return [], {}, {}
        # everything that needs no parameter structure is checked before the simulator is built
        given_space = {p: V.choice(w / "space" / p, s, ["log", "linear"])
                       for p, s in fit.get("space", {}).items()}
        given_bounds = {}
        for p, b in fit.get("bounds", {}).items():
            wp = w / "bounds" / p
            if not isinstance(b, list) or len(b) != 2:
                raise wp.error(f"must be [lo, hi], got {V._kind(b)} {V._show(b)}.")
            lo, hi = (V.number(wp / j, x) for j, x in enumerate(b))
            if not lo < hi:
                raise wp.error(f"needs lo < hi, got [{lo:g}, {hi:g}].")
            given_bounds[p] = (lo, hi)
        try:
            with np.errstate(over="ignore"):      # only the structure is needed here
                sim = dp.compile(self.scene, self.dt, **sf.compile_options)
                params = _default_params(sim, k, c)
            sf._sim = (_x64(), sim)
        except dp.SceneError as exc:
            raise w.error(f"cannot build the parameters: {exc}") from None
        leaves = param_leaves(params)
        alias = _keystr_paths(params)

        def resolve(wp, p):
            p = p.strip()
            if p in leaves:
                return p
            if p in alias:
                return alias[p]
            raise wp.error(f"{p!r} is not a parameter of this scene; its parameters are: "
                           f"{', '.join(leaves) or 'none'}.")
        free = []
        for i, p in enumerate(names):
            q = resolve(w / "params" / i, p)
            if q in free:
                raise (w / "params" / i).error(f"names {q!r} twice.")
            free.append(q)
        space = {p: leaf_space(p, leaves[p]) for p in free}
        for p, s in given_space.items():
            q = resolve(w / "space" / p, p)
            if q not in free:
                raise (w / "space" / p).error(f"sets the space of {q!r}, which is not in [fit] "
                                              "params; add it there.")
            space[q] = s
        bounds = {}
        for p, (lo, hi) in given_bounds.items():
            wp = w / "bounds" / p
            q = resolve(wp, p)
            if q not in free:
                raise wp.error(f"bounds {q!r}, which is not in [fit] params; add it there.")
            v = float(np.asarray(leaves[q]))
            if space.get(q) == "log" and lo <= 0.0:
                raise wp.error(f"has lo = {lo:g} <= 0 for a leaf fitted in log space; give lo "
                               "> 0, or set [fit.space] to \"linear\" for it.")
            if lo < 0.0 and not signed_leaf(q):
                raise wp.error(f"has lo = {lo:g} < 0, but {q!r} cannot be negative (a "
                               "stiffness, damping, friction, slip speed, drag or yield "
                               "strain); give lo >= 0.")
            if not lo <= v <= hi:
                raise wp.error(f"[{lo:g}, {hi:g}] does not contain the start value {v:g} from "
                               "the scene; widen the bounds or change the start value.")
            bounds[q] = (lo, hi)
        for q, s in space.items():
            if s == "log" and float(np.asarray(leaves[q])) <= 0.0:
                raise (w / "params").error(f"{q!r} starts at {float(np.asarray(leaves[q])):g}, "
                                           "which log space cannot hold; give it a positive "
                                           "start value or fit it in linear space.")
        return free, bounds, space
