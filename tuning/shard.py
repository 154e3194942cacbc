"""Spread a batch over every device with ``jax.sharding`` (one machine or many).

``sharded_map(fn)`` turns a per-candidate function into one that evaluates a whole batch with
its leading axis split across a 1-D device ``Mesh`` (``NamedSharding(mesh, P("batch"))``);
results are gathered back and are identical to the single-device ``jax.vmap``. On one device
it is exactly ``jax.jit(jax.vmap(fn))``.

Several processes (hosts): every process calls :func:`tuning.distributed.join` (or
``jax.distributed.initialize``) before anything else (see the README, "Beyond one machine");
``jax.devices()`` then lists the devices of all processes and the same code shards over them.
Every process must have the same number of local devices and run the same function on the same
batch (a call whose batch or function differs between processes stops with the same error on
all of them; functions are compared by their jaxpr); each gets the whole result back
as ordinary arrays on its own first device (the program gathers the rows of every device), so
the results are identical on every process and readable anywhere.
"""
from __future__ import annotations

import hashlib
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from .distributed import check_same, jaxpr_digest

__all__ = ["batch_mesh", "sharded_map", "pad_to_multiple"]


def batch_mesh(devices=None) -> Mesh:
    """A 1-D mesh named ``"batch"`` over ``devices`` (default: all devices, all hosts)."""
    devs = np.asarray(jax.devices() if devices is None else devices)
    return Mesh(devs.reshape(-1), ("batch",))


def pad_to_multiple(tree, multiple: int):
    """Pad every leaf's leading axis to a multiple of ``multiple`` by repeating the last row.

    Returns ``(padded_tree, n)`` with ``n`` the original batch size (slice results ``[:n]``).
    NumPy leaves stay NumPy arrays (on the host), others become ``jax.Array``s.
    """
    leaves = jax.tree_util.tree_leaves(tree)
    if not leaves:
        raise ValueError("sharded_map needs at least one batched array argument.")
    n = int(np.shape(leaves[0])[0])
    extra = (-n) % multiple

    def pad(a):
        xp = np if isinstance(a, np.ndarray) else jnp
        a = xp.asarray(a)
        if a.shape[0] != n:
            raise ValueError(f"all batched arguments need the same leading size; got "
                             f"{a.shape[0]} and {n}.")
        if extra == 0:
            return a
        return xp.concatenate([a, xp.repeat(a[-1:], extra, axis=0)], axis=0)
    return jax.tree_util.tree_map(pad, tree), n


def _host(a) -> np.ndarray:
    """``a`` as a NumPy array of the dtype JAX would give it (float32 without x64)."""
    a = np.asarray(a)
    return a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False)


def _digest(tree) -> bytes:
    """SHA-256 of a pytree of host arrays: their shapes, dtypes and values."""
    leaves = jax.tree_util.tree_leaves(tree)
    h = hashlib.sha256(str(len(leaves)).encode())
    for a in leaves:
        h.update(repr((a.shape, a.dtype.str)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.digest()


def sharded_map(fn: Callable, mesh: Mesh | None = None, *, batched: bool = False,
                what: str = "sharded_map function (compared by its jaxpr: what it computes "
                            "and the arrays it closes over)") -> Callable:
    """``jax.vmap(fn)`` over the leading axis of every argument, sharded over ``mesh``.

    Args:
      fn: per-candidate function of pytrees of arrays (no leading batch axis).
      mesh: a 1-D mesh with axis ``"batch"`` (default: :func:`batch_mesh`).
      batched: ``fn`` already maps over the leading axis of every argument and output (rows
        independent); it is sharded as it is, not wrapped in ``jax.vmap``.
      what: what ``fn`` is, in words, for the error raised when processes pass different
        functions ("processes [1] were given a different WHAT from process 0").
    Returns:
      ``run(*batched_args)``: same outputs as ``jax.vmap(fn)(*batched_args)``. A batch that is
      not a multiple of the device count is padded (by repeating its last row) and the padding
      is dropped from the outputs. The jitted program is built once per mesh, shapes and
      dtypes, so repeated calls with new values do not recompile. Over several processes
      every process passes the same batch and gets the same, whole result. A batch that
      differs between processes raises the same ``ValueError`` on all of them, and so does a
      function that computes something else: before anything runs, the processes compare
      :func:`tuning.distributed.jaxpr_digest` of the traced program (traced once per layout:
      its operations, literals such as dt and step counts, and the arrays it closes over), so
      processes given different functions (another scene, dt, duration or metric) do not mix
      their rows.
    """
    mesh = batch_mesh() if mesh is None else mesh
    n_dev = mesh.devices.size
    spec = NamedSharding(mesh, P("batch"))
    # a mesh over several processes: gather every row onto every device inside the program
    # (a replicated output), so that each process holds the whole result
    processes = len({d.process_index for d in mesh.devices.flat})
    multi = processes > 1
    every = processes == jax.process_count()    # the batch is checked across all processes
    program = jax.jit(fn if batched else jax.vmap(fn), in_shardings=spec,
                      out_shardings=NamedSharding(mesh, P()) if multi else spec)

    digests: dict = {}       # argument layout -> digest of the program traced for it

    def _check_function(placed) -> None:
        """Every process runs the same program: compared on every call (a process that
        skipped the comparison would leave the others waiting in it), traced and digested
        once per argument layout (the trace is the one the call then compiles: ``jit``
        caches it)."""
        leaves, tree = jax.tree_util.tree_flatten(placed)
        layout = (tree, tuple((a.shape, a.dtype.str) for a in leaves))
        if layout not in digests:
            digests[layout] = jaxpr_digest(program.trace(*placed).jaxpr)
        check_same(what, digests[layout])

    def run(*args):
        if multi:     # every process holds the whole batch; each device takes its rows
            host = jax.tree_util.tree_map(_host, args)
            if every:
                check_same("sharded_map batch (the arguments' shapes, dtypes and values)",
                           _digest(host))
            padded, n = pad_to_multiple(host, n_dev)
            placed = jax.tree_util.tree_map(
                lambda a: jax.make_array_from_callback(a.shape, spec, lambda i: a[i]), padded)
            if every:
                _check_function(placed)
            out = program(*placed)
            # replicated: this process's first copy is the whole result
            return jax.tree_util.tree_map(lambda a: a.addressable_data(0)[:n], out)
        padded, n = pad_to_multiple(args, n_dev)
        placed = jax.device_put(padded, spec)
        out = program(*placed)
        return jax.tree_util.tree_map(lambda a: a[:n], out)
    run.mesh = mesh
    run.jitted = program
    return run
