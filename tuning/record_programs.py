"""The compiled residual programs of record fits (:func:`tuning.trajfit.fit_records`): the
residuals of all records' pose loss, their forward-mode Jacobian and the count of rollouts
past the safe step, with the params and the records' arrays as arguments, so that a later fit
of the same layout (simulator, leaves, loss settings, batch shapes) compiles nothing; with
``refine`` the records' start states projected out (:mod:`tuning.start_refine`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import diffpen as dp

from .compiled import ProgramCache
from .free_leaves import with_leaves
from .lm import residuals_and_jacobian
from .pose import pose_residuals, residual_records
from .record_batch import layout_of, simulate, with_arrays
from .start_refine import offset_columns, project_starts, start_steps

__all__ = ["programs"]

#: compiled record-fit programs by (simulator, leaves, loss settings, batch layouts)
_PROGRAMS = ProgramCache()


def programs(sim: dp.Simulator, free, batches, rot_weight, loss, decay, refine=False):
    """``((res_jac_flag, cost_flag), arrays)``: the jitted ``(params, arrays, x, horizon) ->
    (r, J, n_unstable)`` and ``-> (cost, n_unstable)`` of
    :func:`tuning.trajfit.fit_records` for this simulator, these leaves and loss settings
    and these batches' layout (:func:`tuning.record_batch.layout_of`), reused by later fits
    of the same layout, and this fit's arrays. ``n_unstable``: records whose rollout went
    past the safe step; ``refine``: :mod:`tuning.start_refine`."""
    split = [layout_of(b) for b in batches]
    key = (sim, tuple((f.name, f.log) for f in free), float(rot_weight), loss,
           None if decay is None else float(decay), tuple(k for k, _, _ in split), refine)
    layouts = [lay for _, lay, _ in split]
    return _PROGRAMS.get(key, lambda: _build(sim, free, layouts, rot_weight, loss, decay,
                                              refine)), [a for _, _, a in split]


def _build(sim, free, layouts, rot_weight, loss, decay, refine=False):
    """:func:`programs`' pair, compiled on first use."""
    rot = sim.scene.has_rotation
    n_off = max(offset_columns(lay, rot) for lay in layouts) if refine else 0

    def resid_flag(params, arrays, x, horizon, u=None, base=None):
        """residuals and the count of unstable rollouts; ``u`` (refine): start offsets
        shared by the records, added to ``base``, each batch's (R, S) per record"""
        p = with_leaves(params, {f.name: f.from_x(x[i]).astype(sim.dtype)
                                 for i, f in enumerate(free)})
        bs = [with_arrays(lay, a) for lay, a in zip(layouts, arrays)]
        out = [simulate(sim, p, b, with_flag=True, offsets=None if u is None else
                        base[k] + u[None, :offset_columns(b, rot)])
               for k, b in enumerate(bs)]
        r = jnp.concatenate([pose_residuals(o[0], o[1], b, rot_weight=rot_weight,
                                            horizon=horizon, loss=loss, decay=decay)
                             for o, b in zip(out, bs)])
        return r, sum(jnp.count_nonzero(o[2]) for o in out)   # records past the safe step

    @jax.jit
    def res_jac_flag(params, arrays, x, horizon):
        if not refine:
            return residuals_and_jacobian(lambda xx: resid_flag(params, arrays, xx, horizon),
                                          x)
        # each row's record over all batches, and each batch's first record
        rows, firsts, n = [], [], 0
        for lay, a in zip(layouts, arrays):
            rows.append(residual_records(with_arrays(lay, a), loss, rot) + n)
            firsts.append(n)
            n += a["pos"].shape[0]
        rows, zero = np.concatenate(rows), jnp.zeros(n_off, x.dtype)
        sizes = [offset_columns(lay, rot) for lay in layouts]
        # each record's start moved by one Gauss-Newton step of its offsets at x (from the
        # estimate: its error is not small against the residuals), then the projection there
        base = [jnp.zeros((a["pos"].shape[0], m), x.dtype) for a, m in zip(arrays, sizes)]
        r0, js, _ = residuals_and_jacobian(
            lambda uu: resid_flag(params, arrays, x, horizon, uu, base), zero)
        step = start_steps(r0, js, rows, n)
        base = [step[f:f + a["pos"].shape[0], :m] for f, a, m in zip(firsts, arrays, sizes)]
        r, J, bad = residuals_and_jacobian(
            lambda xu: resid_flag(params, arrays, xu[:len(free)], horizon, xu[len(free):],
                                  base), jnp.concatenate([x, zero]))
        r, J = project_starts(r, J[:, :len(free)], J[:, len(free):], rows, n)
        return r, J, bad

    @jax.jit
    def cost_flag(params, arrays, x, horizon):
        r, bad = (res_jac_flag(params, arrays, x, horizon)[::2] if refine else
                  resid_flag(params, arrays, x, horizon))
        return jnp.sum(r * r), bad
    return res_jac_flag, cost_flag
