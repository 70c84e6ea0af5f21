"""exp, tanh, sin and cos that the compiler can vectorise across SIMD lanes, with stated bounds.

numba compiles `np.exp`, `np.sin` and `np.cos` to LLVM intrinsics and `np.tanh` to a libm
call. Without a vector maths library behind them, LLVM cannot put these calls in a vector loop:
it either scalarises the intrinsics (four libm calls per AVX2 vector) or, for the libm call,
gives up on the whole loop. The usual remedy, numba with Intel's SVML (`icc_rt`), needs an
llvmlite built with the SVML patch; this one is not (`numba -s`: "LLVM SVML Patched: False"),
and its LLVM has no `-vector-library` option either, so glibc's libmvec cannot be plugged in.
Hence these: branch-free straight-line code of additions, multiplications, fused
multiply-adds and bit moves, which LLVM turns into AVX2/FMA instructions inside a loop over
joints.

Bounds, relative to the correctly rounded value (checked against glibc in
tests/test_batch_lanes.py on ~10^6 points each):
  * `exp`: at most 2 ulp over the whole double range (overflow to inf above 709.78, 0 below
    -745.13, NaN kept). Cody-Waite reduction x = n ln2 + r, |r| <= ln2/2, then e^r by its Taylor
    polynomial of degree 13, whose truncation error (ln2/2)^14 / 14! = 4e-18 is below half an
    ulp; the rest is the rounding of 13 fused steps.
  * `tanh`: at most 3 ulp: expm1(2|x|) / (expm1(2|x|) + 2), with expm1 by its own Taylor
    polynomial near zero (so tiny arguments keep their relative accuracy) and by `exp` - 1
    where that loses less than an ulp.
  * `sin`, `cos`: at most 2 ulp for |x| <= 2^19 pi/2 (the reduction by pi/2 in three parts of
    33 bits is exact for |n| < 2^20); beyond that the reduction loses bits. Joint positions stay
    within a few radians: a rollout that wanders further has an overflowing barrier cost, which
    the line search rejects whatever the gravity term says.
"""

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, register_jitable


@intrinsic
def fused_multiply_add(typingctx, a, b, c):
    """a b + c with one rounding (llvm.fma): the same result in a vector lane and in scalar
    code, and one instruction on a CPU with FMA."""
    if not all(isinstance(x, types.Float) for x in (a, b, c)):
        return None
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        args = [context.cast(builder, v, t, types.float64)
                for v, t in zip(args, signature.args, strict=True)]
        double = ir.DoubleType()
        fma = cgutils.get_or_insert_function(builder.module,
                                             ir.FunctionType(double, [double] * 3), "llvm.fma.f64")
        return builder.call(fma, args)

    return sig, codegen


@intrinsic
def _bits(typingctx, x):
    """The IEEE-754 bits of a float64 as an int64 (a register move, no memory)."""
    if not isinstance(x, types.Float):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _from_bits(typingctx, i):
    """The float64 whose IEEE-754 bits are the int64 i."""
    if not isinstance(i, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


_ROUNDER = 6755399441055744.0  # 1.5 2^52: x + this rounds x to an integer (|x| < 2^51)
_ROUNDER_BITS = 0x4338000000000000
_LOG2_E = 1.4426950408889634
_LN2_HIGH = 6.93147180369123816490e-01  # ln 2 in 32 bits: n LN2_HIGH is exact for |n| < 2^21
_LN2_LOW = 1.90821492927058770002e-10
# e^r = sum r^k / k!, k = 0..13, highest first
_EXP_TAYLOR = (1.0 / 6227020800.0, 1.0 / 479001600.0, 1.0 / 39916800.0, 1.0 / 3628800.0,
               1.0 / 362880.0, 1.0 / 40320.0, 1.0 / 5040.0, 1.0 / 720.0, 1.0 / 120.0,
               1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0)
_EXP_MAX = 710.0  # e^710 overflows, e^-746 underflows: clamping there changes no result
_EXP_MIN = -746.0


@register_jitable(forceinline=True)
def _round_to_integer(x):
    """x rounded to the nearest integer, as a float and as an int64 (|x| < 2^51)."""
    shifted = x + _ROUNDER
    return shifted - _ROUNDER, _bits(shifted) - _ROUNDER_BITS


@register_jitable(forceinline=True)
def _power_of_two(n):
    """2^n for an int64 |n| <= 1022 (a normal number)."""
    return _from_bits((n + 1023) << 52)


@register_jitable(forceinline=True)
def _exp_reduced(r):
    """e^r for |r| <= ln2/2 (Taylor, degree 13, Horner with fused steps)."""
    c = _EXP_TAYLOR
    e = c[0]
    e = fused_multiply_add(e, r, c[1])
    e = fused_multiply_add(e, r, c[2])
    e = fused_multiply_add(e, r, c[3])
    e = fused_multiply_add(e, r, c[4])
    e = fused_multiply_add(e, r, c[5])
    e = fused_multiply_add(e, r, c[6])
    e = fused_multiply_add(e, r, c[7])
    e = fused_multiply_add(e, r, c[8])
    e = fused_multiply_add(e, r, c[9])
    e = fused_multiply_add(e, r, c[10])
    e = fused_multiply_add(e, r, c[11])
    e = fused_multiply_add(e, r, c[12])
    return fused_multiply_add(e, r, c[13])


@register_jitable(forceinline=True)
def exp(x):
    """e^x within 2 ulp, branch-free (see the module docstring)."""
    clamped = _EXP_MAX if x > _EXP_MAX else x
    clamped = _EXP_MIN if clamped < _EXP_MIN else clamped
    clamped = 0.0 if clamped != clamped else clamped  # NaN: computed on 0, restored below
    n_float, n = _round_to_integer(clamped * _LOG2_E)
    r = clamped - n_float * _LN2_HIGH - n_float * _LN2_LOW
    # 2^n in two factors, so n down to -1075 and up to 1024 stays in the normal range
    half = n >> 1
    e = _exp_reduced(r) * _power_of_two(half) * _power_of_two(n - half)
    return x if x != x else e


_EXPM1_TAYLOR = (1.0 / 6227020800.0, 1.0 / 479001600.0, 1.0 / 39916800.0, 1.0 / 3628800.0,
                 1.0 / 362880.0, 1.0 / 40320.0, 1.0 / 5040.0, 1.0 / 720.0, 1.0 / 120.0,
                 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0)
_TANH_SATURATION = 20.0  # tanh(20) = 1 - 8e-18 rounds to 1


@register_jitable(forceinline=True)
def _expm1_small(y):
    """e^y - 1 for 0 <= y <= ln2/2, with relative accuracy near zero (Taylor, degree 13)."""
    c = _EXPM1_TAYLOR
    e = c[0]
    e = fused_multiply_add(e, y, c[1])
    e = fused_multiply_add(e, y, c[2])
    e = fused_multiply_add(e, y, c[3])
    e = fused_multiply_add(e, y, c[4])
    e = fused_multiply_add(e, y, c[5])
    e = fused_multiply_add(e, y, c[6])
    e = fused_multiply_add(e, y, c[7])
    e = fused_multiply_add(e, y, c[8])
    e = fused_multiply_add(e, y, c[9])
    e = fused_multiply_add(e, y, c[10])
    e = fused_multiply_add(e, y, c[11])
    e = fused_multiply_add(e, y, c[12])
    return e * y


@register_jitable(forceinline=True)
def tanh(x):
    """tanh x within 3 ulp, branch-free (see the module docstring)."""
    magnitude = abs(x)
    y = 2.0 * (_TANH_SATURATION if magnitude > _TANH_SATURATION else magnitude)
    small = _expm1_small(y)
    large = exp(y) - 1.0
    em1 = small if y <= 0.34657359027997264 else large  # both computed: one select per lane
    t = em1 / (em1 + 2.0)
    t = -t if x < 0.0 else t
    return x if x != x else t


_TWO_OVER_PI = 0.63661977236758134308
# pi/2 in three parts of 33 bits and the tail (fdlibm's e_rem_pio2.c)
_PIO2_1 = 1.57079632673412561417e+00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3 = 2.02226624871116645580e-21
_PIO2_3_TAIL = 8.47842766036889956997e-32
# minimax polynomials of fdlibm's k_sin.c and k_cos.c on [-pi/4, pi/4]
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11


@register_jitable(forceinline=True)
def sin_cos(x):
    """(sin x, cos x) within 2 ulp for |x| <= 2^19 pi/2, branch-free (see the module
    docstring): one reduction serves both, as the joint's gravity needs both."""
    finite = x - x == 0.0
    x0 = x if finite else 0.0
    n_float, n = _round_to_integer(x0 * _TWO_OVER_PI)
    r = x0 - n_float * _PIO2_1
    r = r - n_float * _PIO2_2
    r = r - n_float * _PIO2_3
    r = r - n_float * _PIO2_3_TAIL
    z = r * r
    s_poly = fused_multiply_add(fused_multiply_add(fused_multiply_add(fused_multiply_add(
        fused_multiply_add(_S6, z, _S5), z, _S4), z, _S3), z, _S2), z, _S1)
    s = fused_multiply_add(r * z, s_poly, r)
    c_poly = fused_multiply_add(fused_multiply_add(fused_multiply_add(fused_multiply_add(
        fused_multiply_add(_C6, z, _C5), z, _C4), z, _C3), z, _C2), z, _C1)
    half_z = 0.5 * z
    w = 1.0 - half_z
    c = w + (((1.0 - w) - half_z) + z * z * c_poly)
    # quadrant n mod 4: sin x = s, c, -s, -c and cos x = c, -s, -c, s; as selects on its two
    # bits (a select per lane, where a chain of comparisons would become a switch that stops
    # the vectoriser)
    odd = (n & 1) != 0
    sin_r = c if odd else s
    cos_r = s if odd else c
    sin_x = -sin_r if (n & 2) != 0 else sin_r
    cos_x = -cos_r if ((n + 1) & 2) != 0 else cos_r
    nan = x - x  # NaN for inf and NaN
    return (sin_x if finite else nan), (cos_x if finite else nan)

