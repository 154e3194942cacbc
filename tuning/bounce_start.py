"""Where a bounce fit starts (:func:`tuning.bounce.fit_bounce`): the searches that move its
start to where the targets' events occur (:func:`event_search`) and, for apex and settling
time targets, along the curve of k and c that keeps the first apex (:func:`apex_settle_search`).
"""
from __future__ import annotations

import math

import numpy as np

from .stable import FLAG

__all__ = ["EVENT_STEP", "EVENT_STEPS", "event_search", "apex_settle_search"]

#: The event search's step: c times this (or k divided by it) per step, for at most
#: ``EVENT_STEPS`` steps (0.7^40 ~ 6e-7: c from any start down to its lower bound).
EVENT_STEP = 0.7
EVENT_STEPS = 40


def event_search(free, values: dict, need: dict, tg: dict, notes: list, *, kpath: str,
                  cpath: str):
    """Start search for targets that name events (:data:`EVENT_TARGETS`):
    ``run(evaluate, slices, log_lo, log_hi) -> [theta]``, the ``search`` of
    :func:`tuning.fit.fit` (``evaluate(theta) -> (r, J, metrics)``; only the metrics are
    read, so a forward rollout will do).

    At a point where a targeted event is absent (nan: the ball does not rebound, or a contact
    does not end within the rollout) the residuals have no gradient towards it. From the
    start (``values``: ``{kpath: k, cpath: c}``; ``free`` the fitted ones, in order), c is
    multiplied by :data:`EVENT_STEP` step by step (k divided by it once c is at its bound
    or not fitted) until every event ``need`` (``{metric: count}``) names occurs. When only
    later ones are missing and the first bounce is above its target (flights too long for
    the rollout), c is raised (k lowered) instead. Returns [] when the start has the events
    (or no step found them), else the first point that has them; ``notes`` say which.
    """
    def absent(m):
        out = []
        for name, count in need.items():
            v = np.atleast_1d(np.asarray(m[name], dtype=float))[:count]
            out += [f"{name}[{i}]" for i in np.nonzero(~np.isfinite(v))[0]]
        return out

    def usable(m):     # every targeted event, in a rollout inside its safe step
        return not absent(m) and not (FLAG in m and bool(np.any(np.asarray(m[FLAG]))))

    def at(x):
        v = dict(values)
        v.update({p: float(math.exp(t)) for p, t in zip(free, x)})
        return f"k = {v[kpath]:.4g} N/m, c = {v[cpath]:.4g} N s/m"

    def run(evaluate, slices, lo, hi):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        x = np.clip(np.log([values[p] for p in free]), lo, hi)
        m = evaluate(x)[2]
        gone = absent(m)
        if not gone:
            return []
        start = at(x)
        more = True        # more rebound: less damping (or a stiffer contact)
        first = [n for n in ("apex_heights", "restitution") if n in need]
        if first and not any(g.endswith("[0]") for g in gone):
            a = float(np.atleast_1d(np.asarray(m[first[0]], dtype=float))[0])
            more = not a > float(tg[first[0]][0])
        step = math.log(1.0 / EVENT_STEP) * (1.0 if more else -1.0)
        moves = ([(free.index(cpath), -step, "c " + ("lowered" if more else "raised"))]
                 if cpath in free else [])
        if kpath in free:
            moves.append((free.index(kpath), step, "k " + ("raised" if more else "lowered")))
        done, steps = [], 0
        for j, d, what in moves:
            while steps < EVENT_STEPS:
                new = float(np.clip(x[j] + d, lo[j], hi[j]))
                if new == x[j]:
                    break
                x = x.copy()
                x[j] = new
                steps += 1
                if what not in done:
                    done.append(what)
                if usable(evaluate(x)[2]):
                    notes.append(f"start: {', '.join(gone)} absent at {start} (the ball does "
                                 "not rebound, or a contact does not end, within the rollout: "
                                 f"no gradient leads there); {' then '.join(done)} step by "
                                 f"step (x{EVENT_STEP:g}, {steps} step"
                                 f"{'s' if steps > 1 else ''}) to {at(x)}, where the targeted "
                                 "events occur")
                    return [x]
        notes.append(f"start: {', '.join(gone)} absent at {start}; "
                     + (f"{' then '.join(done)} step by step to {at(x)}" if done else
                        "k and c at their bounds") +
                     " found no point where every targeted event occurs, so the fit starts "
                     "where it was and such events are reported as nan")
        return []
    return run


def apex_settle_search(log_ks, log_cs, *, newton: int = 6, bisect: int = 10):
    """Start search for (k, c) from a first-apex (or first-restitution) and a settling-time
    target.

    The settling time is piecewise continuous in (k, c): it jumps whenever a small bounce's
    apex crosses the settling band. A local method stalls at those jumps, so: on a scan over
    k, c is solved by Newton so that the first apex is met exactly (smooth in c); along that
    curve the settling-time residual is bracketed between scan points and bisected in log k.
    A bracket holds either a root or a jump; every bracket's end point is returned, best
    first, for Levenberg-Marquardt to polish.
    """
    def run(evaluate, slices, lo, hi):
        # the first apex, or the first restitution where no apex is targeted (the same
        # curve: both fix the first rebound)
        ia = slices["apex_heights" if "apex_heights" in slices else "restitution"].start
        js = slices["settling_time"].start

        def on_curve(lk, lc):
            r = None
            for _ in range(newton):
                r, J, _ = evaluate(np.array([lk, lc]))
                r, J = np.asarray(r), np.asarray(J)
                if not np.all(np.isfinite(r)) or abs(r[ia]) < 1e-5 or J[ia, 1] == 0.0:
                    break
                lc = float(np.clip(lc - np.clip(r[ia] / J[ia, 1], -0.5, 0.5), lo[1], hi[1]))
            return lc, r

        pts = []
        for lk, lc in zip(log_ks, log_cs):
            lk = float(np.clip(lk, lo[0], hi[0]))
            if pts:   # warm start: same damping ratio as the previous point on the curve
                lc = pts[-1][1] + 0.5 * (lk - pts[-1][0])
            lc, r = on_curve(lk, float(np.clip(lc, lo[1], hi[1])))
            if r is not None and np.all(np.isfinite(r)):
                pts.append((lk, lc, r))
        out = []
        for (ka, ca, ra), (kb, cb, rb) in zip(pts[:-1], pts[1:]):
            if np.sign(ra[js]) == np.sign(rb[js]):
                continue
            for _ in range(bisect):
                km = 0.5 * (ka + kb)
                cm, rm = on_curve(km, 0.5 * (ca + cb))
                if not np.all(np.isfinite(rm)):
                    break
                if np.sign(rm[js]) == np.sign(ra[js]):
                    ka, ca, ra = km, cm, rm
                else:
                    kb, cb, rb = km, cm, rm
            out += [(float(ra @ ra), ka, ca), (float(rb @ rb), kb, cb)]
        out += [(float(r @ r), k, c) for k, c, r in pts]
        out.sort()
        return [np.array([k, c]) for _, k, c in out[:6]]
    return run
