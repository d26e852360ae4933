"""A float32 dot product for the compiled kernels whose order of additions is fixed by this code, not by the
compiler (numba; imported only with :mod:`sdfcodec_pca.kernels`).

Why: a sum compiled with fastmath's ``reassoc`` is vectorised however the code generator likes, and the machine
code a process compiled for itself and the code numba loaded from its on-disk cache reassociated one kernel's sums
differently: the same blocks got codes up to 3.4 apart (a refit's active set follows the decode), so a map
depended on whether the kernels had been compiled in the process. Without ``reassoc`` LLVM keeps a sum in source
order and does not vectorise it; :func:`dot` writes the vector form out itself: eight lanes of explicit
``<8 x float>`` multiplies and adds (the callers' fastmath adds only ``contract``: a lane's multiply and add may
fuse, never reorder; each lane rounds the same whether the machine runs it as one AVX register or two SSE ones),
the lanes then added in one fixed tree, then the tail in order."""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["dot", "dot4"]

_LANES = 8


def _vector(a) -> bool:
    return isinstance(a, types.Array) and a.ndim == 1 and a.dtype == types.float32 and a.layout == "C"


def _dots(context, builder, x, x_type, rows, row_types, count):
    """The IR of ``[x[:count] . r[:count] for r in rows]`` in :func:`dot`'s order, one pass reading ``x`` once."""
    vec = ir.VectorType(ir.FloatType(), _LANES)
    px = context.make_array(x_type)(context, builder, x).data
    prs = [context.make_array(ty)(context, builder, r).data for r, ty in zip(rows, row_types)]
    lanes_of = ir.Constant(count.type, _LANES)
    full = builder.sdiv(count, lanes_of)
    accs = [cgutils.alloca_once_value(builder, ir.Constant(vec, [0.0] * _LANES)) for _ in prs]
    with cgutils.for_range(builder, full) as loop:
        at = builder.mul(loop.index, lanes_of)
        vx = builder.load(builder.bitcast(builder.gep(px, [at]), vec.as_pointer()), align=4)
        for pr, acc in zip(prs, accs):
            vr = builder.load(builder.bitcast(builder.gep(pr, [at]), vec.as_pointer()), align=4)
            builder.store(builder.fadd(builder.load(acc), builder.fmul(vx, vr)), acc)
    start = builder.mul(full, lanes_of)
    out = []
    for pr, acc in zip(prs, accs):
        lanes = builder.load(acc)
        e = [builder.extract_element(lanes, ir.Constant(ir.IntType(32), i)) for i in range(_LANES)]
        pairs = [builder.fadd(e[i], e[i + 1]) for i in range(0, _LANES, 2)]
        total = cgutils.alloca_once_value(
            builder, builder.fadd(builder.fadd(pairs[0], pairs[1]), builder.fadd(pairs[2], pairs[3])))
        with cgutils.for_range_slice(builder, start, count, ir.Constant(count.type, 1)) as (j, _):
            term = builder.fmul(builder.load(builder.gep(px, [j])), builder.load(builder.gep(pr, [j])))
            builder.store(builder.fadd(builder.load(total), term), total)
        out.append(builder.load(total))
    return out


@intrinsic
def dot(typingctx, x, y, n):
    """``x[:n] . y[:n]`` as float32 for C-contiguous float32 vectors ``x`` and ``y`` (at least ``n`` long; not
    checked, as the kernels' own indexing is not): lane ``l`` sums ``x[8i + l] y[8i + l]`` in order of ``i``, the
    eight lanes add as ``((l0 + l1) + (l2 + l3)) + ((l4 + l5) + (l6 + l7))``, then the ``n mod 8`` last products
    add in order."""
    if not (_vector(x) and _vector(y) and isinstance(n, types.Integer)):
        return None  # numba then reports that no signature matches

    def codegen(context, builder, sig, args):
        count = context.cast(builder, args[2], sig.args[2], types.intp)
        return _dots(context, builder, args[0], sig.args[0], args[1:2], sig.args[1:2], count)[0]

    return types.float32(x, y, n), codegen


@intrinsic
def dot4(typingctx, x, r0, r1, r2, r3, n):
    """``(x . r0, x . r1, x . r2, x . r3)`` over the first ``n`` elements, each exactly :func:`dot`'s, in one
    pass that reads ``x`` once (a decode of four voxels' basis rows)."""
    if not (all(_vector(a) for a in (x, r0, r1, r2, r3)) and isinstance(n, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        count = context.cast(builder, args[5], sig.args[5], types.intp)
        dots = _dots(context, builder, args[0], sig.args[0], args[1:5], sig.args[1:5], count)
        return context.make_tuple(builder, sig.return_type, dots)

    return types.UniTuple(types.float32, 4)(x, r0, r1, r2, r3, n), codegen
