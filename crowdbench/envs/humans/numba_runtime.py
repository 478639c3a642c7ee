"""What the compiled crowd kernels (``orca_kernel``, ``sfm_kernel``) share: numba's threading layer, its
thread count, and one lock around their parallel launches."""

from __future__ import annotations

import os
import threading

import torch

LOCK = threading.Lock()  # the workqueue layer must not be entered by two threads at once (any kernel)
OPTIONS = {"cache": True, "fastmath": False, "error_model": "numpy"}  # no fastmath: no FMA, no reordering


def numba_module():
    """numba, imported on first use, with the workqueue threading layer unless the user chose one."""
    import numba

    if "NUMBA_THREADING_LAYER" not in os.environ:
        # workqueue, not OpenMP: after a parallel region OpenMP's workers spin, taking the cores from
        # torch's threads; on 2 busy cores (load ~10) the 20-human world ran 3x faster with workqueue.
        # (Only until numba's first parallel launch in the process: then the layer is fixed.)
        numba.config.THREADING_LAYER = "workqueue"
    return numba


def set_threads() -> None:
    """As many numba threads as torch's intra-op threads (the world's ``--threads``)."""
    import numba

    want = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    if numba.get_num_threads() != want:
        numba.set_num_threads(want)


def compile_module(g: dict, helpers, solve, inline=()):
    """Compile a kernel module in place, lazily (importing it does not import numba): each function of
    ``g`` (the module's globals) named in ``helpers`` (and ``inline``: inlined in numba's IR, where a call
    would stop a loop's vectorisation) replaced by its compiled version, ``g["_prange"]`` by numba's
    ``prange``; returns ``solve`` compiled parallel over worlds (loaded from the cache when it can be)."""
    numba = numba_module()
    g["_prange"] = numba.prange
    for name in inline:
        g[name] = numba.njit(inline="always", **OPTIONS)(g[name])
    for name in helpers:
        g[name] = numba.njit(**OPTIONS)(g[name])
    return numba.njit(parallel=True, **OPTIONS)(solve)
