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

__all__ = ["dot"]

_LANES = 8


def _vector(a) -> bool:
    return isinstance(a, types.Array) and a.ndim == 1 and a.dtype == types.float32 and a.layout == "C"


@intrinsic
def dot(typingctx, x, y, n):
    """``x[:n] . y[:n]`` as float32 for C-contiguous float32 vectors ``x`` and ``y`` (at least ``n`` long; not
    checked, as the kernels' own indexing is not): lane ``l`` sums ``x[8i + l] y[8i + l]`` in order of ``i``, the
    eight lanes add as ``((l0 + l1) + (l2 + l3)) + ((l4 + l5) + (l6 + l7))``, then the ``n mod 8`` last products
    add in order."""
    if not (_vector(x) and _vector(y) and isinstance(n, types.Integer)):
        return None  # numba then reports that no signature matches

    def codegen(context, builder, sig, args):
        vec = ir.VectorType(ir.FloatType(), _LANES)
        px = context.make_array(sig.args[0])(context, builder, args[0]).data
        py = context.make_array(sig.args[1])(context, builder, args[1]).data
        count = context.cast(builder, args[2], sig.args[2], types.intp)
        lanes_of = ir.Constant(count.type, _LANES)
        full = builder.sdiv(count, lanes_of)
        acc = cgutils.alloca_once_value(builder, ir.Constant(vec, [0.0] * _LANES))
        with cgutils.for_range(builder, full) as loop:
            at = builder.mul(loop.index, lanes_of)
            vx = builder.load(builder.bitcast(builder.gep(px, [at]), vec.as_pointer()), align=4)
            vy = builder.load(builder.bitcast(builder.gep(py, [at]), vec.as_pointer()), align=4)
            builder.store(builder.fadd(builder.load(acc), builder.fmul(vx, vy)), acc)
        lanes = builder.load(acc)
        e = [builder.extract_element(lanes, ir.Constant(ir.IntType(32), i)) for i in range(_LANES)]
        pairs = [builder.fadd(e[i], e[i + 1]) for i in range(0, _LANES, 2)]
        total = cgutils.alloca_once_value(
            builder, builder.fadd(builder.fadd(pairs[0], pairs[1]), builder.fadd(pairs[2], pairs[3])))
        start = builder.mul(full, lanes_of)
        with cgutils.for_range_slice(builder, start, count, ir.Constant(count.type, 1)) as (j, _):
            term = builder.fmul(builder.load(builder.gep(px, [j])), builder.load(builder.gep(py, [j])))
            builder.store(builder.fadd(builder.load(total), term), total)
        return builder.load(total)

    return types.float32(x, y, n), codegen
