"""Numba helpers shared by the compiled per-hop kernels of ``estimators`` and ``beamform`` (public: beamform
imports it from here; it depends on numba and numpy alone)."""

from __future__ import annotations

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

EXPONENT_MASK = np.uint32(0x7F800000)  # float32 exponent bits: all set <=> inf or NaN


@numba.njit(cache=True, nogil=True)
def all_finite(bits: np.ndarray) -> bool:
    """True if no float32 in ``bits`` (their uint32 view) is inf or NaN (exponent bits all set).

    An integer max-reduction: it vectorises without reordering float sums and cannot overflow.
    """
    top = np.uint32(0)
    for t in range(bits.shape[0]):
        top = max(top, bits[t] & EXPONENT_MASK)
    return top != EXPONENT_MASK


@intrinsic
def borrowed(typingctx, arr):
    """``arr`` without its reference count: the same data, shape and strides, a null meminfo.

    Every view a kernel takes of an array (``x[i]``, ``x[a:b]``, ``.reshape``, ``.T``) and every
    array it passes to a function that is not inlined increments and decrements the array's
    reference count, an atomic (``lock``-prefixed) instruction that waits for the store buffer to
    drain: a hop made ~760 of them (found with ``perf`` and a gdb breakpoint on ``NRT_incref``).
    On views of a borrowed array these are a null check. Only for arrays that outlive the call (the
    arguments of a compiled entry point, kept alive by the caller) and never returned or stored.
    """
    if not isinstance(arr, types.Array):
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, value=args[0])
        ary.meminfo = ary.meminfo.type(None)  # null: NRT_incref / NRT_decref skip it
        return ary._getvalue()

    return arr(arr), codegen
