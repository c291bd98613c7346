"""Numba helpers shared by the compiled per-hop kernels of ``estimators`` and ``beamform`` (public: beamform
imports it from here; it depends on numba alone)."""

from __future__ import annotations

from numba.core import types
from numba.extending import intrinsic


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
