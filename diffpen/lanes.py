"""Batched lanes: helpers for ``jax.custom_vmap`` rules that treat each element of a batch
on its own.

Under ``jax.vmap`` a ``lax.cond`` on a batched predicate runs both branches on every lane,
so an expensive branch that one rollout takes in a few steps is paid for by every lane in
every step. A ``custom_vmap`` rule sees the whole batch and can do better; these are the
pieces such rules share:

* :func:`lined_up`: a rule's values, batched or not, broadcast to one common
  (batch,) + lane shape (the window's batched rule, :mod:`diffpen.window`, and
  :func:`by_lanes`);
* :func:`by_lanes`: an elementwise solve run only on the lanes that need it, gathered
  :data:`LANES_PER_PASS` at a time, with derivatives of the plain solve (the event-exact
  records' crossing, :mod:`diffpen.event_step`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

__all__ = ["LANES_PER_PASS", "lined_up", "by_lanes"]


def lined_up(axis_size: int, in_batched, values) -> list:
    """A ``custom_vmap`` rule's ``values`` (batched ones with the batch axis in front, the
    others without it), each lane's broadcast together (e.g. (n,) and ()), lined up on the
    lane's shape behind the batch axis: every one (axis_size,) + lane."""
    lanes = [jnp.shape(x)[1:] if b else jnp.shape(x) for x, b in zip(values, in_batched)]
    lane = jnp.broadcast_shapes(*lanes)

    def lined(x, b, shape):
        if b:
            x = jnp.reshape(x, (axis_size,) + (1,) * (len(lane) - len(shape)) + shape)
        return jnp.broadcast_to(x, (axis_size,) + lane)
    return [lined(x, b, sh) for x, b, sh in zip(values, in_batched, lanes)]



#: lanes a batched step solves at a time (:func:`by_lanes`)
LANES_PER_PASS = 32


def by_lanes(general):
    """``general(*args) -> out`` (the crossing's every-case solve: elementwise, without
    ``lax.cond``) as ``call(need, fill, *args)``, whose batched form solves only the lanes
    where ``need`` and gives ``fill`` elsewhere.

    One rollout calls the crossing only in the steps next to a crossing (the callers'
    ``lax.cond``), on every contact: ``call`` is ``general`` there (``need`` and ``fill``
    unused). Under ``jax.vmap`` a ``lax.cond`` on a batched predicate runs both branches on
    every lane, so every lane paid for the Newton solve in every step (~100x the default
    record's cost at 1024 balls). The batched form (a ``custom_vmap`` rule) gathers the
    lanes where ``need`` :data:`LANES_PER_PASS` at a time (as many passes as there are such
    lanes; none in most steps), solves them, and each such lane reads its result back from
its pass (the others keep ``fill``; no scatter, which would end XLA CPU's single-kernel
rollout loop; where more than a quarter of the lanes need it, every lane is solved). The
    callers pass as ``fill`` what ``general`` gives on the other lanes (the parabola apart,
    the spring's motion in contact: the same operations), so the values are ``general``'s,
    lane by lane. Derivatives are ``general``'s on every lane (a ``custom_jvp`` rule: its
    forward- and reverse-mode cost is unchanged; the rule holds no ``lax.cond``, whose
    derivative inside a ``custom_jvp`` rule under ``jax.vmap`` and ``lax.scan`` does not
    transpose in JAX 0.10)."""
    def call(need, fill, *args):
        # Python numbers (the step h) stay static: closed over, as the callers have them
        static = {i: v for i, v in enumerate(args) if isinstance(v, (int, float))}
        leaves, tree = jax.tree_util.tree_flatten(
            (fill, [v for i, v in enumerate(args) if i not in static]))

        def unflat(ls):
            fill, dynamic = jax.tree_util.tree_unflatten(tree, ls)
            dynamic = iter(dynamic)
            return fill, [static[i] if i in static else next(dynamic)
                          for i in range(len(args))]

        @custom_vmap
        def batched(need, *ls):
            return general(*unflat(ls)[1])

        @batched.def_vmap
        def _rule(axis_size, in_batched, need, *ls):
            # every value to (axis_size,) + lane, then flat: one lane per element
            lined = lined_up(axis_size, in_batched, [need, *ls])
            shape = jnp.shape(lined[0])
            need, *flat = [jnp.reshape(v, (-1,)) for v in lined]
            fill, args = unflat(flat)
            n = need.shape[0]
            # the pass that starts at the need-lane numbered `done` takes the lanes whose running
            # count of need-lanes reaches done + 1 ... done + m (binary searches), and each
            # lane reads its result back from the pass by its own number (a gather)
            running = jnp.cumsum(need.astype(jnp.int32))
            count = running[-1]
            m = min(LANES_PER_PASS, n)
            slots = jnp.arange(1, m + 1, dtype=jnp.int32)

            def gathered(sel):
                return [v if isinstance(v, (int, float)) else
                        jax.tree_util.tree_map(lambda w: w[sel], v) for v in args]

            def one_pass(state):
                out, done = state
                sel = jnp.minimum(jnp.searchsorted(running, done + slots, side="left",
                                                   method="scan_unrolled"), n - 1)
                res = general(*gathered(sel))
                mine = running - 1 - done           # this lane's slot in the pass
                take = need & (mine >= 0) & (mine < m)
                at = jnp.clip(mine, 0, m - 1)
                out = jax.tree_util.tree_map(lambda o, r: jnp.where(take, r[at], o), out, res)
                return out, done + m

            def passes(_):
                return jax.lax.while_loop(lambda st: st[1] < count, one_pass,
                                          (fill, jnp.zeros((), jnp.int32)))[0]

            def every_lane(_):          # most lanes need it (a resting Hertz ball's shooting)
                return jax.tree_util.tree_map(lambda r, f: jnp.where(need, r, f),
                                              general(*args), fill)
            out = jax.lax.cond(4 * count > n, every_lane, passes, None)
            out = jax.tree_util.tree_map(lambda o: jnp.reshape(o, shape), out)
            return out, jax.tree_util.tree_map(lambda _: True, out)

        @jax.custom_jvp
        def differentiable(need, *ls):
            return batched(need, *ls)

        @differentiable.defjvp
        def _jvp(primals, tangents):
            return jax.jvp(lambda *ls: general(*unflat(ls)[1]), primals[1:], tangents[1:])
        return differentiable(need, *leaves)
    return call
