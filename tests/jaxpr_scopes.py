"""Shared test helper: the ``jax.named_scope`` names in a simulator step's traced program."""
import jax
from jax.extend.core import jaxprs_in_params


def traced_scopes(sim, params):
    """``(names, jaxpr)``: the set of name stacks of every equation in ``sim.step``'s jaxpr
    (nested jaxprs included), and the jaxpr itself."""
    jaxpr = jax.make_jaxpr(sim.step)(params, sim.init_state())
    names = set()

    def walk(jx):
        for eqn in jx.eqns:
            names.add(str(eqn.source_info.name_stack))
            for sub in jaxprs_in_params(eqn.params):
                walk(sub)
    walk(jaxpr.jaxpr)
    return names, jaxpr
