"""tuning.params: leaf paths are the jax.tree_util key paths joined by dots; unflatten
replaces only the named leaves and keeps the pytree's structure."""
import jax
import numpy as np

import diffpen as dp
from diffpen.state import ContactParams, SpringParams
from tuning import params as P

PARAMS = dp.Params({"steel": ContactParams(np.float64(2e5), np.float64(3.0)),
                    "rubber": ContactParams(np.float64(1e4), np.float64(10.0))},
                   {"rope": SpringParams(np.float64(50.0), np.float64(0.5))},
                   {"drag": {"rope": np.float64(0.2)}, "slip": np.float64(1e-3)})


def test_paths_come_from_the_tree_key_paths():
    flat = P.flatten(PARAMS)
    # jax.tree_util order: fields in order, dict keys sorted
    assert list(flat) == ["contact.rubber.k", "contact.rubber.c", "contact.steel.k",
                          "contact.steel.c", "springs.rope.k", "springs.rope.c",
                          "extra.drag.rope", "extra.slip"]
    assert flat["contact.steel.k"] == 2e5 and flat["extra.drag.rope"] == 0.2
    keyed = jax.tree_util.tree_flatten_with_path(PARAMS)[0]
    assert [P.path_name(path) for path, _ in keyed] == list(flat)
    assert list(P.leaf_paths(PARAMS)) == list(flat) == P.paths(PARAMS)
    assert P.leaf_paths(PARAMS)["contact.steel.c"] == keyed[3][0]
    assert P.default_free(PARAMS) == list(flat)[:4]


def test_unflatten_replaces_only_the_named_leaves():
    new = P.unflatten(PARAMS, {"contact.steel.c": 7.0, "extra.drag.rope": 0.4,
                               "springs.nothing.k": 1.0})
    assert jax.tree_util.tree_structure(new) == jax.tree_util.tree_structure(PARAMS)
    assert isinstance(new.contact["steel"], ContactParams)
    assert new.contact["steel"].c == 7.0 and new.extra["drag"]["rope"] == 0.4
    assert new.contact["steel"].k == 2e5 and new.extra["slip"] == 1e-3
    assert new.contact["rubber"] == PARAMS.contact["rubber"]
    assert P.flatten(P.unflatten(PARAMS, P.flatten(PARAMS))) == P.flatten(PARAMS)
