/* SO(3) maps exp / log / sqrt and their backward passes (issues 6, 11; loaded by
 * torchconn/ops/native.py, the CPU kernels of the torchconn::so3_* custom ops of
 * torchconn/ops/so3.py).
 *
 * Every element kernel mirrors a torch formula of torchconn/ops/_so3_formulas.py operation by operation,
 * in the same dtype and the same order of operations, so that the two paths agree to round-off
 * and take the same branch decisions (compiled with -std=c99, hence -ffp-contract=off: no FMA
 * contraction that the torch kernels would not do either):
 *
 *   exp  : exp_coeffs + rodrigues                     backward: exp_bwd
 *   log  : log_parts                                  backward: log_bwd, the chain rule of the same
 *          expressions (what torch autograd computes on them, including at exactly pi,
 *          where the derivative of atan2 at (0, c = -1) is finite)
 *   sqrt : sqrt (half-angle identity for tr R > 0, exp(log(R)/2) otherwise); backward: sqrt_bwd,
 *          the exact derivative of the same expressions for every 3x3 input (not only rotations)
 *
 * Layout: contiguous row-major, omega (n, 3), matrices (n, 3, 3) = (n, 9); grad_out of the
 * backward may be strided: entry k of element i at grad_out[i * gs_elem + k * gs_comp] (in
 * elements of T; contiguous: (3 or 9, 1); the gradient of a sum is a broadcast one, (0, 0),
 * read without being materialized).
 * Exported symbols: so3_{exp,log,sqrt}_{fwd,bwd}_{f32,f64}, so3_log_fwd_checked_{f32,f64}
 *   fwd(const T* in, T* out, long n, int nthreads, double eps)
 *   bwd(const T* in, const T* grad_out, T* grad_in, long n, int nthreads, double eps,
 *       long gs_elem, long gs_comp)
 *   long log_fwd_checked(const T* R, T* w, long n, int nthreads, double eps, double tol,
 *                        long* first): log_fwd, and the count / first index of the matrices
 *                        that are not rotations within tol (computed in the same pass, from
 *                        the nine entries already loaded: no second pass over memory)
 * where eps is torchconn.tolerances.get_eps("small_angle", dtype) (the Taylor threshold is
 * compared as |.|^2 < (T)(eps*eps), the same rounding as torch's tensor < python-float).
 *
 * Speed: as in torch, every branch is evaluated on every element and the result selected
 * (no data-dependent jumps), and elements are processed in blocks of SO3_B, copied to
 * component-major buffers, so that the compiler vectorizes the element loop (#pragma omp
 * simd). sin, cos and atan2 are written out below as branch-free polynomials (sincos,
 * atan2v) for that: libm calls vectorize only where GCC finds a libmvec variant of the vector
 * width it picked (with GCC 12 and glibc 2.36, log and sqrt ran scalar on AVX2, exp and sqrt
 * on AVX-512; glibc < 2.35 has no vector atan2). The results agree with torch's to round-off
 * (the tests hold the two paths to 1e-6 in float32 and 1e-12 in float64). Unused branches get
 * values that may be inf or NaN; they are discarded by the selects (no floating-point traps
 * are enabled).
 * Also exported for the tests: so3_sincos_SUF(t, s, c, n), so3_atan2_SUF(y, x, out, n).
 *
 * Validation (so3_log_fwd_checked): the residual ||R^T R - I||_F^2 and det R are ~40 more
 * multiply-adds per element on the nine entries already in registers, in the same vectorized
 * loop, with one flag per element written to a spare row of the block buffer and summed per
 * block (per task a count and a first index, combined with atomics: neither depends on the
 * order); a separate torch check (more passes over memory) costs 10-20x the op.
 *
 * Threads: the loops run as tasks of SO3_TASK_BLOCKS blocks on the pool of pool.c (pool.c).
 *
 * The two dtypes are instantiated by including this file into itself with T = float, double.
 *
 * Included by another kernel file with SO3_KERNELS_ONLY defined (tet.c), this file gives that
 * file its element kernels and the block helpers sqrt_{fwd,bwd}_block_{f32,f64} (static: one
 * home for the formulas), without the exported loops; native.py's cache key hashes the
 * including file and this one.
 */
#ifndef SO3_T

#include <math.h>

#if defined(__GNUC__) && !defined(__clang__)
/* Keep every branch computed on every element, so that the element loops have no control
 * flow and vectorize: jump threading and sinking would move operations into the branch that
 * uses them, and an operation under a condition is if-converted (executed on every lane,
 * its result selected) only if it cannot trap, which for floating-point arithmetic GCC
 * assumes only under -fno-trapping-math (without it the loops vectorized only with AVX-512's
 * masked operations). No floating-point traps are enabled here, and the option changes no
 * value (no reassociation, no contraction). Restored at the end of this file (pop), so that
 * a file including this one keeps its own options. */
#pragma GCC push_options
#pragma GCC optimize("no-thread-jumps", "no-tree-sink", "no-trapping-math")
#endif


/* The trigonometric functions of the element kernels are written out below (FN(sincos),
 * FN(atan2v)): branch-free polynomials that the vectorizer inlines like any arithmetic, on
 * every ISA and with any C compiler and libm. Calls to libm's sinf / atan2f in the element
 * loop would vectorize only where the compiler finds a vector variant for the exact vector
 * width it chose (glibc >= 2.35 libmvec, GCC, `simd` declarations): with GCC 12 on an
 * AVX-512 CPU (256-bit vectors preferred) exp did not vectorize, on AVX2 log and sqrt did not,
 * and glibc < 2.35 has no vector atan2 at all. libm is kept only as the exact path of exp
 * blocks holding an angle beyond the reduction's range (SO3_TRIG_MAX). */

#define SO3_CAT_(a, b) a##b
#define SO3_CAT(a, b) SO3_CAT_(a, b)
/* loops smaller than this run on the calling thread (no pool wake-up) */
#define SO3_PAR_MIN 4096L
/* elements per block (component-major buffers of 3 x 9 x SO3_B values stay in L1) */
#define SO3_B 128
/* blocks per task of the pool (2048 elements, ~5-50 us of work) */
#define SO3_TASK_BLOCKS 16L
/* the nine statements S(0) ... S(8), written out: a loop inside the vectorized element loop
 * would be control flow that stops GCC's vectorizer */
#define SO3_EACH9(S) S(0) S(1) S(2) S(3) S(4) S(5) S(6) S(7) S(8)

/* kernels run by SO3_RUNNER: inlined there whatever their size (a call stops the vectorizer) */
#define SO3_INLINE __attribute__((always_inline)) static inline

/* The vectorized element loop of KERN(A, Bg, O, j, eps2) on the m elements of a block, as a
 * function of its own (a runner: with two such loops in one function GCC 12 vectorizes only
 * one of them). SO3_RUNNER_TOL: KERN also takes tol2. */
#define SO3_RUNNER(NAME, KERN)                                                                \
    __attribute__((noinline)) static void NAME(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O,   \
                                               int m, T eps2, T tol2)                         \
    {                                                                                         \
        (void)tol2;                                                                           \
        _Pragma("omp simd")                                                                   \
        for (int j = 0; j < m; ++j)                                                           \
            KERN(A, Bg, O, j, eps2);                                                          \
    }
#define SO3_RUNNER_TOL(NAME, KERN)                                                            \
    __attribute__((noinline)) static void NAME(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O,   \
                                               int m, T eps2, T tol2)                         \
    {                                                                                         \
        _Pragma("omp simd")                                                                   \
        for (int j = 0; j < m; ++j)                                                           \
            KERN(A, Bg, O, j, eps2, tol2);                                                    \
    }

#define TC_POOL_CLIENT
#include "pool.c" /* tc_parallel */

/* 8 x 8 (float) and 4 x 4 (double) register transposes for the copies between rows of 9
 * components and a block's component rows (rows_in9 / rows_out9 below): the lane shuffles of
 * the classic AVX sequence (unpack, shuffle, 128-bit permute), written with the compiler's
 * generic vector extension, so that every ISA gets its own instructions (two 128-bit halves
 * where vectors are 128 bits). Element-wise copies of 9 components are scalar loads and
 * stores: they were ~3/4 of exp's time (10^6 rotations). */
#if defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 12)
#define SO3_TRANSPOSE 1
typedef float so3_v8f __attribute__((vector_size(32), aligned(4), may_alias));
typedef double so3_v4d __attribute__((vector_size(32), aligned(8), may_alias));
#define SO3_SHUF __builtin_shufflevector
static inline void so3_t8x8(so3_v8f r[8])
{
    so3_v8f t0 = SO3_SHUF(r[0], r[1], 0, 8, 1, 9, 4, 12, 5, 13), t1 = SO3_SHUF(r[0], r[1], 2, 10, 3, 11, 6, 14, 7, 15);
    so3_v8f t2 = SO3_SHUF(r[2], r[3], 0, 8, 1, 9, 4, 12, 5, 13), t3 = SO3_SHUF(r[2], r[3], 2, 10, 3, 11, 6, 14, 7, 15);
    so3_v8f t4 = SO3_SHUF(r[4], r[5], 0, 8, 1, 9, 4, 12, 5, 13), t5 = SO3_SHUF(r[4], r[5], 2, 10, 3, 11, 6, 14, 7, 15);
    so3_v8f t6 = SO3_SHUF(r[6], r[7], 0, 8, 1, 9, 4, 12, 5, 13), t7 = SO3_SHUF(r[6], r[7], 2, 10, 3, 11, 6, 14, 7, 15);
    so3_v8f u0 = SO3_SHUF(t0, t2, 0, 1, 8, 9, 4, 5, 12, 13), u1 = SO3_SHUF(t0, t2, 2, 3, 10, 11, 6, 7, 14, 15);
    so3_v8f u2 = SO3_SHUF(t1, t3, 0, 1, 8, 9, 4, 5, 12, 13), u3 = SO3_SHUF(t1, t3, 2, 3, 10, 11, 6, 7, 14, 15);
    so3_v8f u4 = SO3_SHUF(t4, t6, 0, 1, 8, 9, 4, 5, 12, 13), u5 = SO3_SHUF(t4, t6, 2, 3, 10, 11, 6, 7, 14, 15);
    so3_v8f u6 = SO3_SHUF(t5, t7, 0, 1, 8, 9, 4, 5, 12, 13), u7 = SO3_SHUF(t5, t7, 2, 3, 10, 11, 6, 7, 14, 15);
    r[0] = SO3_SHUF(u0, u4, 0, 1, 2, 3, 8, 9, 10, 11); r[4] = SO3_SHUF(u0, u4, 4, 5, 6, 7, 12, 13, 14, 15);
    r[1] = SO3_SHUF(u1, u5, 0, 1, 2, 3, 8, 9, 10, 11); r[5] = SO3_SHUF(u1, u5, 4, 5, 6, 7, 12, 13, 14, 15);
    r[2] = SO3_SHUF(u2, u6, 0, 1, 2, 3, 8, 9, 10, 11); r[6] = SO3_SHUF(u2, u6, 4, 5, 6, 7, 12, 13, 14, 15);
    r[3] = SO3_SHUF(u3, u7, 0, 1, 2, 3, 8, 9, 10, 11); r[7] = SO3_SHUF(u3, u7, 4, 5, 6, 7, 12, 13, 14, 15);
}
static inline void so3_t4x4(so3_v4d r[4])
{
    so3_v4d t0 = SO3_SHUF(r[0], r[1], 0, 4, 2, 6), t1 = SO3_SHUF(r[0], r[1], 1, 5, 3, 7);
    so3_v4d t2 = SO3_SHUF(r[2], r[3], 0, 4, 2, 6), t3 = SO3_SHUF(r[2], r[3], 1, 5, 3, 7);
    r[0] = SO3_SHUF(t0, t2, 0, 1, 4, 5); r[2] = SO3_SHUF(t0, t2, 2, 3, 6, 7);
    r[1] = SO3_SHUF(t1, t3, 0, 1, 4, 5); r[3] = SO3_SHUF(t1, t3, 2, 3, 6, 7);
}
#endif

#define SO3_T float
#define SO3_F32 1
#define SO3_SUF _f32
#define SO3_SIN sinf
#define SO3_COS cosf
#define SO3_SQRT sqrtf
#define SO3_FABS fabsf
#define SO3_COPYSIGN copysignf
#include "so3.c" /* this file, again (quoted includes resolve next to it) */
#undef SO3_T
#undef SO3_F32
#undef SO3_SUF
#undef SO3_SIN
#undef SO3_COS
#undef SO3_SQRT
#undef SO3_FABS
#undef SO3_COPYSIGN

#define SO3_T double
#define SO3_F32 0
#define SO3_SUF _f64
#define SO3_SIN sin
#define SO3_COS cos
#define SO3_SQRT sqrt
#define SO3_FABS fabs
#define SO3_COPYSIGN copysign
#include "so3.c" /* this file, again (quoted includes resolve next to it) */
#undef SO3_T
#undef SO3_F32
#undef SO3_SUF
#undef SO3_SIN
#undef SO3_COS
#undef SO3_SQRT
#undef SO3_FABS
#undef SO3_COPYSIGN

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC pop_options
#endif

#else /* ------------------------------------------------------------- one dtype */

#define T SO3_T
#define FN(name) SO3_CAT(name, SO3_SUF)
#define K(x) ((T)(x))
typedef T FN(blk_t)[SO3_B];

/* ---------------------------------------------------------------- sin, cos, atan2
 *
 * Branch-free (every lane the same instructions, selects, no calls), so the element loops
 * vectorize whatever the ISA and the libm. Largest errors measured against long-double
 * references (tests/test_native_so3.py, test_trig_*): sin, cos 2.4 ulp (0.74 eps absolute),
 * atan2 2.6 ulp, in float32 and float64 (torch's SLEEF kernels: 1 ulp; glibc's libmvec: 4).
 *
 * sincos(t), |t| < SO3_TRIG_MAX: t = n pi/2 + r, |r| <= pi/4, n rounded to the nearest
 * integer by (x + 1.5 2^p) - 1.5 2^p and n mod 4 taken the same way (in floating point: no
 * integer lanes); r by Cody-Waite subtraction of pi/2 split in parts whose products with n
 * are exact (float: four parts, three of <= 11 bits, |n| < 2^13; double: three, two of 33
 * bits, |n| < 2^20); sin r = r + r z S(z), cos r = 1 - z/2 + z^2 C(z), z = r^2, Chebyshev fits
 * (mpmath) of degree 2 (float) / 5 (double); the quadrant swaps and negates. NaN and inf give
 * NaN (as libm). Beyond SO3_TRIG_MAX the reduction loses accuracy: exp routes blocks holding
 * such angles to libm (trig_ok, below), the other callers never reach it (|angle| <= pi / 2).
 *
 * atan2v(y, x): C99's atan2 in every IEEE case (signed zeros, infinities, NaN):
 * a = min(|x|,|y|) / max(|x|,|y|) in [0, 1], atan a = pi/4 + atan((a-1)/(a+1)) for
 * a > tan(pi/8), atan b = b + b z P(z) on |b| <= tan(pi/8) (degree 4 (float) / 10 (double));
 * then the octant: k + s p with k a multiple of pi/4 (in two parts), s = +-1, the sign of y.
 */
#if SO3_F32
#define SO3_RND 0x1.8p23f                  /* (x + RND) - RND: x rounded to an integer, |x| < 2^22 */
#define SO3_TRIG_MAX 8192.0f               /* |n| <= 5216 < 2^13 */
#define SO3_2_PI 0x1.45f306p-1f
#define SO3_PIO2_1 0x1.92p+0f              /* pi/2 = P1 + P2 + P3 + P4 (P1 .. P3: <= 11 bits) */
#define SO3_PIO2_2 0x1.fb4p-12f
#define SO3_PIO2_3 0x1.444p-24f
#define SO3_PIO2_4 0x1.68c234p-39f
#define SO3_SIN_POLY(z) (-0x1.555552p-3f + (z) * (0x1.110c28p-7f + (z) * -0x1.9ac9bp-13f))
#define SO3_COS_POLY(z) (0x1.555554p-5f + (z) * (-0x1.6c12d2p-10f + (z) * 0x1.9bd89cp-16f))
#define SO3_ATAN_POLY(z) (-0x1.555554p-2f + (z) * (0x1.99973p-3f + (z) * (-0x1.242036p-3f \
        + (z) * (0x1.b8103p-4f + (z) * -0x1.08455ep-4f))))
#define SO3_TAN_PI8 0x1.a8279ap-2f
#define SO3_PIO4_HI 0x1.921fb6p-1f
#define SO3_PIO4_LO -0x1.777a5cp-26f
#define SO3_PIO2_HI 0x1.921fb6p+0f
#define SO3_PIO2_LO -0x1.777a5cp-25f
#define SO3_3PIO4_HI 0x1.2d97c8p+1f
#define SO3_3PIO4_LO -0x1.99bc5cp-28f
#define SO3_PI_HI 0x1.921fb6p+1f
#define SO3_PI_LO -0x1.777a5cp-24f
#else
#define SO3_RND 0x1.8p52
#define SO3_TRIG_MAX 65536.0               /* |n| <= 41723 < 2^20 */
#define SO3_2_PI 0x1.45f306dc9c883p-1
#define SO3_PIO2_1 0x1.921fb544p+0         /* pi/2 = P1 + P2 + P3 (P1, P2: 33 bits each) */
#define SO3_PIO2_2 0x1.0b4611a6p-34
#define SO3_PIO2_3 0x1.3198a2e037073p-69
#define SO3_SIN_POLY(z) (-0x1.5555555555555p-3 + (z) * (0x1.1111111110bb2p-7 \
        + (z) * (-0x1.a01a019e83aaep-13 + (z) * (0x1.71de37968a100p-19 \
        + (z) * (-0x1.ae600b02b6262p-26 + (z) * 0x1.5e0b19f8b1451p-33)))))
#define SO3_COS_POLY(z) (0x1.5555555555555p-5 + (z) * (-0x1.6c16c16c16967p-10 \
        + (z) * (0x1.a01a019f4eb01p-16 + (z) * (-0x1.27e4fa17da09ep-22 \
        + (z) * (0x1.1eeb68e93b64cp-29 + (z) * -0x1.907da367a37cbp-37)))))
#define SO3_ATAN_POLY(z) (-0x1.5555555555555p-2 + (z) * (0x1.999999999934cp-3 \
        + (z) * (-0x1.2492492436201p-3 + (z) * (0x1.c71c71853d7fap-4 \
        + (z) * (-0x1.745d0b28a7e37p-4 + (z) * (0x1.3b1263064f6b9p-4 \
        + (z) * (-0x1.10fa77b1a6d57p-4 + (z) * (0x1.dfe6497e96323p-5 \
        + (z) * (-0x1.a0999c632b6edp-5 + (z) * (0x1.4162c02b1dda3p-5 \
        + (z) * -0x1.3a31b1c0fd3b7p-6))))))))))
#define SO3_TAN_PI8 0x1.a827999fcef32p-2
#define SO3_PIO4_HI 0x1.921fb54442d18p-1
#define SO3_PIO4_LO 0x1.1a62633145c07p-55
#define SO3_PIO2_HI 0x1.921fb54442d18p+0
#define SO3_PIO2_LO 0x1.1a62633145c07p-54
#define SO3_3PIO4_HI 0x1.2d97c7f3321d2p+1
#define SO3_3PIO4_LO 0x1.a79394c9e8a0ap-54
#define SO3_PI_HI 0x1.921fb54442d18p+1
#define SO3_PI_LO 0x1.1a62633145c07p-53
#endif

SO3_INLINE void FN(sincos)(T t, T *s, T *c)
{
    T n = (t * SO3_2_PI + SO3_RND) - SO3_RND;
    /* q = n mod 4 in floating point (integer lanes of the width of double need SSE4.1):
     * n - 4 round(n/4) is in {-2, ..., 2} */
    T d = n - K(4.0) * ((K(0.25) * n + SO3_RND) - SO3_RND);
    T q = d + K(4.0) * (T)(d < K(0.0));
#if SO3_F32
    T r = (((t - n * SO3_PIO2_1) - n * SO3_PIO2_2) - n * SO3_PIO2_3) - n * SO3_PIO2_4;
#else
    T r = ((t - n * SO3_PIO2_1) - n * SO3_PIO2_2) - n * SO3_PIO2_3;
#endif
    T z = r * r;
    T sr = r + r * z * SO3_SIN_POLY(z);
    T hz = K(0.5) * z, w = K(1.0) - hz;
    T cr = w + (((K(1.0) - w) - hz) + z * z * SO3_COS_POLY(z));  /* 1 - hz, its rounding added back */
    int odd = (q == K(1.0)) | (q == K(3.0));
    T ss = odd ? cr : sr, cc = odd ? sr : cr;
    *s = q >= K(2.0) ? -ss : ss;                       /* n mod 4 = 2, 3: sin < 0 */
    *c = (q == K(1.0)) | (q == K(2.0)) ? -cc : cc;     /* n mod 4 = 1, 2: cos < 0 */
}

SO3_INLINE T FN(atan2v)(T y, T x)
{
    T ax = SO3_FABS(x), ay = SO3_FABS(y);
    int swap = ay > ax;  /* false for a NaN: mx = NaN (ax) or mn = NaN (ay), a = NaN */
    T mx = swap ? ay : ax, mn = swap ? ax : ay;
    int inf2 = (ax == (T)INFINITY) & (ay == (T)INFINITY);  /* a = inf/inf: atan a = pi/4 */
    /* All arithmetic unconditional, only its results selected (an operation under a
     * condition stops the vectorizer unless it is if-converted, see the pragma above). */
    T a = mn / (mx + (T)(mx == K(0.0)));  /* (0, 0): 0 / 1 */
    int big = (a > SO3_TAN_PI8) | inf2;
    T b_big = (a - K(1.0)) / (a + K(1.0));
    T b = big ? b_big : a;
    T z = b * b;
    T p = b + b * z * SO3_ATAN_POLY(z);
    p = inf2 ? K(0.0) : p;
    /* atan2 = k + s p, k in {0, pi/4, pi/2, 3pi/4, pi}, s = +-1 (from big, swap and the sign
     * of x): atan a = big pi/4 + p; swapped, pi/2 - atan a; x < 0, pi - that. k in two parts,
     * added last: one rounding, and the exact k at the axes and diagonals */
    int neg = SO3_COPYSIGN(K(1.0), x) < K(0.0);  /* x < 0 or x = -0 */
    T k4 = big ? K(1.0) : K(0.0);          /* k in units of pi/4 */
    k4 = swap ? K(2.0) - k4 : k4;
    k4 = neg ? K(4.0) - k4 : k4;
    int minus = swap ^ neg;
    T k_hi = k4 == K(1.0) ? SO3_PIO4_HI : k4 == K(2.0) ? SO3_PIO2_HI : k4 == K(3.0) ? SO3_3PIO4_HI
           : k4 == K(4.0) ? SO3_PI_HI : K(0.0);
    T k_lo = k4 == K(1.0) ? SO3_PIO4_LO : k4 == K(2.0) ? SO3_PIO2_LO : k4 == K(3.0) ? SO3_3PIO4_LO
           : k4 == K(4.0) ? SO3_PI_LO : K(0.0);
    T r = k_hi + (k_lo + (minus ? -p : p));
    return SO3_COPYSIGN(r, y);
}

#undef SO3_RND
#undef SO3_2_PI
#undef SO3_PIO2_1
#undef SO3_PIO2_2
#undef SO3_PIO2_3
#undef SO3_PIO2_4
#undef SO3_SIN_POLY
#undef SO3_COS_POLY
#undef SO3_ATAN_POLY
#undef SO3_TAN_PI8
#undef SO3_PIO4_HI
#undef SO3_PIO4_LO
#undef SO3_PIO2_HI
#undef SO3_PIO2_LO
#undef SO3_3PIO4_HI
#undef SO3_3PIO4_LO
#undef SO3_PI_HI
#undef SO3_PI_LO

/* ---------------------------------------------------------------- the blocked loop */

typedef void (*FN(run_t))(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int m, T eps2, T tol2);
typedef int (*FN(if_t))(FN(blk_t) *A, int m);

#ifndef SO3_KERNELS_ONLY
/* One blocked loop over n elements: per block of SO3_B elements, the rows of `a` (na = 3 or 9
 * components) and `b` (nb = 0, 3 or 9) are copied into component-major buffers, a runner
 * computes O (`fast` on a block where fast_if holds, else `kern`) and its nout rows go back
 * into the rows of `out`. With flag >= 0, row `flag` of O holds a 0/1 flag per element:
 * nbad counts them, first is the smallest flagged index (n if none). The tasks of the pool
 * are runs of SO3_TASK_BLOCKS blocks; every element is computed the same way whichever thread
 * runs it, and count and minimum do not depend on the order. */
typedef struct {
    const T *a, *b;
    T *out;
    long n, b_es, b_cs;  /* with b_strided: b's strides (element, component) */
    int na, nb, nout, flag, b_strided;
    FN(run_t) kern, fast;
    FN(if_t) fast_if;
    T eps2, tol2;
    long nbad, first;
} FN(loop_t);

/* the m rows of K components at src into the columns of D (K a constant where inlined) */
SO3_INLINE void FN(rows_in)(FN(blk_t) *D, const T *src, int m, int K)
{
    for (int k = 0; k < K; ++k)  /* k outer: ~10-25% faster than j outer (9 components) */
        for (int j = 0; j < m; ++j)
            D[k][j] = src[(long)j * K + k];
}

/* the same from a strided source: component k of row j at src[j * es + k * cs] */
static void FN(rows_in_strided)(FN(blk_t) *D, const T *src, int m, int K, long es, long cs)
{
    for (int k = 0; k < K; ++k)
        for (int j = 0; j < m; ++j)
            D[k][j] = src[(long)j * es + k * cs];
}

SO3_INLINE void FN(rows_out)(T *dst, FN(blk_t) *D, int m, int K)
{
    for (int j = 0; j < m; ++j)
        for (int k = 0; k < K; ++k)
            dst[(long)j * K + k] = D[k][j];
}

/* rows_in / rows_out for 9 components: groups of 8 (float) / 4 (double) rows through register
 * transposes (components 0-7; the 9th one by one), the rest element-wise (the same values) */
static void FN(rows_in9)(FN(blk_t) *D, const T *src, int m)
{
    int j0 = 0;
#ifdef SO3_TRANSPOSE
#if SO3_F32
    for (; j0 + 8 <= m; j0 += 8) {
        so3_v8f r[8];
        for (int e = 0; e < 8; ++e)
            r[e] = *(const so3_v8f *)(src + 9L * (j0 + e));
        so3_t8x8(r);
        for (int k = 0; k < 8; ++k)
            *(so3_v8f *)&D[k][j0] = r[k];
        for (int e = 0; e < 8; ++e)
            D[8][j0 + e] = src[9L * (j0 + e) + 8];
    }
#else
    for (; j0 + 4 <= m; j0 += 4) {
        for (int h = 0; h < 8; h += 4) {
            so3_v4d r[4];
            for (int e = 0; e < 4; ++e)
                r[e] = *(const so3_v4d *)(src + 9L * (j0 + e) + h);
            so3_t4x4(r);
            for (int k = 0; k < 4; ++k)
                *(so3_v4d *)&D[h + k][j0] = r[k];
        }
        for (int e = 0; e < 4; ++e)
            D[8][j0 + e] = src[9L * (j0 + e) + 8];
    }
#endif
#endif
    for (int k = 0; k < 9; ++k)
        for (int j = j0; j < m; ++j)
            D[k][j] = src[9L * j + k];
}

static void FN(rows_out9)(T *dst, FN(blk_t) *D, int m)
{
    int j0 = 0;
#ifdef SO3_TRANSPOSE
#if SO3_F32
    for (; j0 + 8 <= m; j0 += 8) {
        so3_v8f r[8];
        for (int k = 0; k < 8; ++k)
            r[k] = *(const so3_v8f *)&D[k][j0];
        so3_t8x8(r);
        for (int e = 0; e < 8; ++e) {
            *(so3_v8f *)(dst + 9L * (j0 + e)) = r[e];
            dst[9L * (j0 + e) + 8] = D[8][j0 + e];
        }
    }
#else
    for (; j0 + 4 <= m; j0 += 4) {
        for (int h = 0; h < 8; h += 4) {
            so3_v4d r[4];
            for (int k = 0; k < 4; ++k)
                r[k] = *(const so3_v4d *)&D[h + k][j0];
            so3_t4x4(r);
            for (int e = 0; e < 4; ++e)
                *(so3_v4d *)(dst + 9L * (j0 + e) + h) = r[e];
        }
        for (int e = 0; e < 4; ++e)
            dst[9L * (j0 + e) + 8] = D[8][j0 + e];
    }
#endif
#endif
    for (int j = j0; j < m; ++j)
        for (int k = 0; k < 9; ++k)
            dst[9L * j + k] = D[k][j];
}

static void FN(loop_task)(void *vc, long task)
{
    FN(loop_t) *c = (FN(loop_t) *)vc;
    T A_[9][SO3_B], B_[9][SO3_B], O_[9][SO3_B];
    const long nblk = (c->n + SO3_B - 1) / SO3_B;
    const long b0 = task * SO3_TASK_BLOCKS;
    const long b1 = b0 + SO3_TASK_BLOCKS < nblk ? b0 + SO3_TASK_BLOCKS : nblk;
    long nbad = 0, first = c->n;
    for (long blk = b0; blk < b1; ++blk) {
        const long i0 = blk * SO3_B;
        const int m = (int)(c->n - i0 < SO3_B ? c->n - i0 : SO3_B);
        if (c->na == 9)
            FN(rows_in9)(A_, c->a + i0 * 9, m);
        else
            FN(rows_in)(A_, c->a + i0 * 3, m, 3);
        if (c->b_strided && (c->b_es != c->nb || c->b_cs != 1))
            FN(rows_in_strided)(B_, c->b + i0 * c->b_es, m, c->nb, c->b_es, c->b_cs);
        else if (c->nb == 9)
            FN(rows_in9)(B_, c->b + i0 * 9, m);
        else if (c->nb == 3)
            FN(rows_in)(B_, c->b + i0 * 3, m, 3);
        (c->fast && c->fast_if(A_, m) ? c->fast : c->kern)(A_, B_, O_, m, c->eps2, c->tol2);
        if (c->nout == 9)
            FN(rows_out9)(c->out + i0 * 9, O_, m);
        else
            FN(rows_out)(c->out + i0 * 3, O_, m, 3);
        if (c->flag >= 0) {
            int cnt = 0;
            for (int j = 0; j < m; ++j)
                cnt += O_[c->flag][j] != K(0.0);
            if (cnt) {
                nbad += cnt;
                for (int j = 0; j < m; ++j)
                    if (O_[c->flag][j] != K(0.0)) {
                        if (i0 + j < first)
                            first = i0 + j;
                        break;
                    }
            }
        }
    }
    if (nbad) {
        __atomic_add_fetch(&c->nbad, nbad, __ATOMIC_RELAXED);
        long cur = __atomic_load_n(&c->first, __ATOMIC_RELAXED);
        while (first < cur && !__atomic_compare_exchange_n(&c->first, &cur, first, 0, __ATOMIC_RELAXED,
                                                           __ATOMIC_RELAXED))
            ;
    }
}

static void FN(loop)(FN(loop_t) *c, int nt)
{
    c->nbad = 0;
    c->first = c->n;
    tc_parallel(tc_tasks((c->n + SO3_B - 1) / SO3_B, SO3_TASK_BLOCKS), c->n >= SO3_PAR_MIN ? nt : 1,
                FN(loop_task), c);
}
#endif /* SO3_KERNELS_ONLY */

/* ---------------------------------------------------------------- exp */

/* A = sin t / t, B = (1 - cos t) / t^2 and, if der, dA/d(t^2), dB/d(t^2) (_so3_formulas.exp_coeffs,
 * whose trigonometric branch gets t^2 = 1 where the Taylor one is used; here t^2 = eps^2) */
SO3_INLINE void FN(exp_coeffs)(T t2, T eps2, int der, int vm, T *A, T *B, T *dA, T *dB)
{
    int small = t2 < eps2;
    /* unused trigonometric branch at t^2 = eps^2 (not a constant: GCC would fold sin(1) and
     * split the loop body into two paths, which stops vectorization) */
    T ts2 = small ? eps2 : t2;
    T t = SO3_SQRT(ts2), s, c;
    if (vm)  /* a constant where inlined: sincos (vectorized), or libm (|t| > SO3_TRIG_MAX) */
        FN(sincos)(t, &s, &c);
    else {
        s = SO3_SIN(t);
        c = SO3_COS(t);
    }
    T omc = K(1.0) - c;
    /* both branches computed, then selected (a conditional division would stop vectorization) */
    T A_t = s / t, B_t = omc / ts2;
    T A_s = K(1.0) - t2 * (K(1.0 / 6.0) - t2 / K(120.0));
    T B_s = K(0.5) - t2 * (K(1.0 / 24.0) - t2 / K(720.0));
    *A = small ? A_s : A_t;
    *B = small ? B_s : B_t;
    if (der) {
        T dA_t = (t * c - s) / (K(2.0) * ts2 * t);
        T dB_t = (t * s - K(2.0) * omc) / (K(2.0) * ts2 * ts2);
        T dA_s = K(-1.0 / 6.0) + t2 * (K(1.0 / 60.0) - t2 / K(1680.0));
        T dB_s = K(-1.0 / 24.0) + t2 * (K(1.0 / 360.0) - t2 / K(13440.0));
        *dA = small ? dA_s : dA_t;
        *dB = small ? dB_s : dB_t;
    }
}

/* R = I + A K + B K^2, K = hat(x, y, z), entries written out (_so3_formulas.rodrigues) */
SO3_INLINE void FN(exp1)(T x, T y, T z, T eps2, int vm, T *r)
{
    T A, B;
    FN(exp_coeffs)(x * x + y * y + z * z, eps2, 0, vm, &A, &B, 0, 0);
    T Bx = B * x, By = B * y;
    T Ax = A * x, Ay = A * y, Az = A * z;
    T bxy = Bx * y, bxz = Bx * z, byz = By * z;
    T xx = x * x, yy = y * y, zz = z * z;
    r[0] = K(1.0) - B * (yy + zz); r[1] = bxy - Az;                r[2] = bxz + Ay;
    r[3] = bxy + Az;                r[4] = K(1.0) - B * (xx + zz); r[5] = byz - Ax;
    r[6] = bxz - Ay;                r[7] = byz + Ax;                r[8] = K(1.0) - B * (xx + yy);
}

/* dL/dw from G = dL/dR (_so3_formulas.exp_bwd) */
SO3_INLINE void FN(exp_bwd1)(T x, T y, T z, const T *G, T eps2, int vm, T *gw)
{
    T t2 = x * x + y * y + z * z, A, B, dA, dB;
    FN(exp_coeffs)(t2, eps2, 1, vm, &A, &B, &dA, &dB);
    T g00 = G[0], g01 = G[1], g02 = G[2], g10 = G[3], g11 = G[4], g12 = G[5], g20 = G[6],
      g21 = G[7], g22 = G[8];
    T gx = g21 - g12, gy = g02 - g20, gz = g10 - g01;
    T tr = g00 + g11 + g22;
    T s01 = g01 + g10, s02 = g02 + g20, s12 = g12 + g21;
    T Sx = K(2.0) * g00 * x + s01 * y + s02 * z;
    T Sy = s01 * x + K(2.0) * g11 * y + s12 * z;
    T Sz = s02 * x + s12 * y + K(2.0) * g22 * z;
    T wGw = K(0.5) * (x * Sx + y * Sy + z * Sz);
    T wg = x * gx + y * gy + z * gz;
    T radial = K(2.0) * dA * wg + K(2.0) * dB * (wGw - t2 * tr) - K(2.0) * B * tr;
    gw[0] = A * gx + B * Sx + radial * x;
    gw[1] = A * gy + B * Sy + radial * y;
    gw[2] = A * gz + B * Sz + radial * z;
}

SO3_INLINE void FN(exp_fwd_k)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2, int vm)
{
    (void)Bg;
    T r[9];
    FN(exp1)(A[0][j], A[1][j], A[2][j], eps2, vm, r);
#define SO3_S(k) O[k][j] = r[k];
    SO3_EACH9(SO3_S)
#undef SO3_S
}

SO3_INLINE void FN(exp_bwd_k)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2, int vm)
{
    T G[9], gw[3];
#define SO3_S(k) G[k] = Bg[k][j];
    SO3_EACH9(SO3_S)
#undef SO3_S
    FN(exp_bwd1)(A[0][j], A[1][j], A[2][j], G, eps2, vm, gw);
    O[0][j] = gw[0]; O[1][j] = gw[1]; O[2][j] = gw[2];
}

#ifndef SO3_KERNELS_ONLY
/* the exp kernels with the written-out sincos (vm) and with libm's sin and cos (lm) */
#define SO3_EXP_K(NAME, KERN, VM)                                                             \
    SO3_INLINE void NAME(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2)            \
    {                                                                                         \
        KERN(A, Bg, O, j, eps2, VM);                                                          \
    }
SO3_EXP_K(FN(exp_fwd_vm_k), FN(exp_fwd_k), 1)
SO3_EXP_K(FN(exp_fwd_lm_k), FN(exp_fwd_k), 0)
SO3_EXP_K(FN(exp_bwd_vm_k), FN(exp_bwd_k), 1)
SO3_EXP_K(FN(exp_bwd_lm_k), FN(exp_bwd_k), 0)
#undef SO3_EXP_K
SO3_RUNNER(FN(exp_fwd_vm_run), FN(exp_fwd_vm_k))
SO3_RUNNER(FN(exp_fwd_lm_run), FN(exp_fwd_lm_k))
SO3_RUNNER(FN(exp_bwd_vm_run), FN(exp_bwd_vm_k))
SO3_RUNNER(FN(exp_bwd_lm_run), FN(exp_bwd_lm_k))

/* Blocks whose every angle |w| is below SO3_TRIG_MAX (or NaN) run the vectorized sincos, the
 * others libm's sin and cos (the reduction is exact only up to there). */
static int FN(trig_ok)(FN(blk_t) *A, int m)
{
    int ok = 1;
    for (int j = 0; j < m; ++j)
        ok &= !(A[0][j] * A[0][j] + A[1][j] * A[1][j] + A[2][j] * A[2][j] >= SO3_TRIG_MAX * SO3_TRIG_MAX);
    return ok;
}

void FN(so3_exp_fwd)(const T *w, T *R, long n, int nt, double eps)
{
    FN(loop_t) c = {.a = w, .b = w, .out = R, .n = n, .na = 3, .nb = 0, .nout = 9, .flag = -1,
                    .kern = FN(exp_fwd_lm_run), .fast = FN(exp_fwd_vm_run), .fast_if = FN(trig_ok),
                    .eps2 = (T)(eps * eps)};
    FN(loop)(&c, nt);
}

void FN(so3_exp_bwd)(const T *w, const T *gR, T *gw, long n, int nt, double eps, long gs_elem, long gs_comp)
{
    FN(loop_t) c = {.a = w, .b = gR, .out = gw, .n = n, .b_es = gs_elem, .b_cs = gs_comp, .na = 3, .nb = 9,
                    .nout = 3, .flag = -1, .b_strided = 1,
                    .kern = FN(exp_bwd_lm_run), .fast = FN(exp_bwd_vm_run), .fast_if = FN(trig_ok),
                    .eps2 = (T)(eps * eps)};
    FN(loop)(&c, nt);
}
#endif /* SO3_KERNELS_ONLY */

/* ---------------------------------------------------------------- log */

/* The branches of _so3_formulas.log_parts, all evaluated, one selected. v = vee(R) = sin(t) n,
 * c = (tr R - 1)/2:
 *   small   (|v|^2 < eps^2 and c > 0): w = (1 + s2 (1/6 + s2 (3/40 + s2 5/112))) v
 *   obtuse  (c < 0): u = column of sym(R) - c I with the largest diagonal entry (the first
 *           one on ties), sgn = sign(u.v) (+1 at 0), w = atan2(sgn u.v / |u|, c) sgn / |u| u
 *   generic (otherwise): w = atan2(|v|, c) / |v| v
 * A NaN entry fails every comparison and takes the generic branch, as in torch. Both atan2
 * share one call (y = sgn u.v/|u| or |v|, x = c). */
typedef struct {
    T vx, vy, vz, c, s2;
    int small, obtuse, p0, p1;  /* branch; pick of the column (p0: 0, p1: 1, else 2) */
    T ux, uy, uz, uvr, inv, sgn, nv, s, a;  /* a = atan2(nv or s, c) */
} FN(logp_t);

static inline void FN(log_parts)(const T *r, T eps2, FN(logp_t) *q)
{
    T vx = K(0.5) * (r[7] - r[5]), vy = K(0.5) * (r[2] - r[6]), vz = K(0.5) * (r[3] - r[1]);
    T c = K(0.5) * (r[0] + r[4] + r[8] - K(1.0));
    T s2 = vx * vx + vy * vy + vz * vz;
    int small = (s2 < eps2) & (c > K(0.0));
    int obtuse = c < K(0.0);
    T d0 = r[0] - c, d1 = r[4] - c, d2 = r[8] - c;
    T o01 = K(0.5) * (r[1] + r[3]), o02 = K(0.5) * (r[2] + r[6]), o12 = K(0.5) * (r[5] + r[7]);
    int p0 = (d0 >= d1) & (d0 >= d2);
    int p1 = !p0 & (d1 >= d2);
    T ux = p0 ? d0 : (p1 ? o01 : o02);
    T uy = p0 ? o01 : (p1 ? d1 : o12);
    T uz = p0 ? o02 : (p1 ? o12 : d2);
    T uu = ux * ux + uy * uy + uz * uz;
    T inv = K(1.0) / SO3_SQRT(uu);  /* inf where unused (uu = 0 at R = I): discarded */
    T uvr = ux * vx + uy * vy + uz * vz;
    T uv = uvr * inv;
    T sgn = uv < K(0.0) ? K(-1.0) : K(1.0);
    T nv = uv * sgn;
    T s = SO3_SQRT(s2);
    q->a = FN(atan2v)(obtuse ? nv : s, c);
    q->vx = vx; q->vy = vy; q->vz = vz; q->c = c; q->s2 = s2;
    q->small = small; q->obtuse = obtuse; q->p0 = p0; q->p1 = p1;
    q->ux = ux; q->uy = uy; q->uz = uz; q->uvr = uvr; q->inv = inv; q->sgn = sgn; q->nv = nv;
    q->s = s;
}

static inline T FN(log_poly)(T s2)
{
    return K(1.0) + s2 * (K(1.0 / 6.0) + s2 * (K(3.0 / 40.0) + s2 * K(5.0 / 112.0)));
}

static inline void FN(log1)(const T *r, T eps2, T *w)
{
    FN(logp_t) q;
    FN(log_parts)(r, eps2, &q);
    T fac_g = q.a / q.s, fac_s = FN(log_poly)(q.s2);
    T fac = q.small ? fac_s : fac_g;
    T k = q.a * q.inv * q.sgn;  /* obtuse: w = k u */
    w[0] = q.obtuse ? k * q.ux : fac * q.vx;
    w[1] = q.obtuse ? k * q.uy : fac * q.vy;
    w[2] = q.obtuse ? k * q.uz : fac * q.vz;
}

/* dL/dR from gw = dL/dw: reverse mode through the expressions of log1, the gradient of each
 * intermediate as torch autograd forms it on _so3_formulas.log_parts (= log_bwd) (sgn and the picks are
 * constants; the gradient of atan2(y, x) is (x, -y) / (x^2 + y^2), finite at (0, -1), i.e. at
 * angle exactly pi). */
static inline void FN(log_bwd1)(const T *r, const T *gw, T eps2, T *gr)
{
    FN(logp_t) q;
    FN(log_parts)(r, eps2, &q);
    T vx = q.vx, vy = q.vy, vz = q.vz, c = q.c, s2 = q.s2;
    T gwv = gw[0] * vx + gw[1] * vy + gw[2] * vz;
    /* -- obtuse: w = k u, k = tp inv sgn, tp = atan2(nv, c), nv = uv sgn, uv = (u.v) inv */
    T ux = q.ux, uy = q.uy, uz = q.uz, inv = q.inv, sgn = q.sgn, nv = q.nv, tp = q.a;
    T k = tp * inv * sgn;
    T gk = gw[0] * ux + gw[1] * uy + gw[2] * uz;
    T gu0 = k * gw[0], gu1 = k * gw[1], gu2 = k * gw[2];
    T gtp = gk * inv * sgn, ginv = gk * tp * sgn;
    T den_o = nv * nv + c * c;
    T gnv = gtp * c / den_o, gc_o = -gtp * nv / den_o;
    T al = gnv * sgn * inv;  /* d/d(u.v) */
    gu0 += al * vx; gu1 += al * vy; gu2 += al * vz;
    T gvx_o = al * ux, gvy_o = al * uy, gvz_o = al * uz;
    ginv += gnv * sgn * q.uvr;
    T be = -ginv * inv * inv * inv;  /* inv = rsqrt(u.u) */
    gu0 += be * ux; gu1 += be * uy; gu2 += be * uz;
    /* u = column of sym(R) - c I: diagonal d_k = r_kk - c, off-diagonal o_kl = (r_kl + r_lk)/2 */
    int p0 = q.p0, p1 = q.p1, p2 = !(p0 | p1), ob = q.obtuse;
    T zero = K(0.0);
    T gd0 = ob & p0 ? gu0 : zero, gd1 = ob & p1 ? gu1 : zero, gd2 = ob & p2 ? gu2 : zero;
    T go01 = ob ? (p0 ? gu1 : (p1 ? gu0 : zero)) : zero;
    T go02 = ob ? (p0 ? gu2 : (p2 ? gu0 : zero)) : zero;
    T go12 = ob ? (p1 ? gu2 : (p2 ? gu1 : zero)) : zero;
    gc_o = gc_o - (gd0 + gd1 + gd2);
    /* -- small: w = poly(s2) v */
    T fac_s = FN(log_poly)(s2);
    T dfac = K(1.0 / 6.0) + s2 * (K(2.0 * 3.0 / 40.0) + s2 * K(3.0 * 5.0 / 112.0));
    T g2_s = K(2.0) * gwv * dfac;  /* 2 dL/ds2: s2 = |v|^2 */
    /* -- generic: w = f v, f = a / s, a = atan2(s, c), s = sqrt(s2) */
    T s = q.s, a = q.a;
    T fac_g = a / s;
    T ga = gwv / s;
    T den_g = s * s + c * c;
    T gs = -gwv * a / (s * s) + ga * c / den_g;
    T gc_g = -ga * s / den_g;
    T g2_g = gs / s;  /* d|v|/dv = v / s */
    /* -- select: w = fac v (small, generic) has dL/dv = fac gw + g2 v */
    T fac = q.small ? fac_s : fac_g, g2 = q.small ? g2_s : g2_g;
    T gvx = ob ? gvx_o : fac * gw[0] + g2 * vx;
    T gvy = ob ? gvy_o : fac * gw[1] + g2 * vy;
    T gvz = ob ? gvz_o : fac * gw[2] + g2 * vz;
    T gc = ob ? gc_o : (q.small ? zero : gc_g);
    /* c = (r00 + r11 + r22 - 1)/2, v = ((r21 - r12), (r02 - r20), (r10 - r01))/2 */
    T hc = K(0.5) * gc;
    gr[0] = gd0 + hc; gr[4] = gd1 + hc; gr[8] = gd2 + hc;
    gr[1] = K(0.5) * go01 - K(0.5) * gvz; gr[3] = K(0.5) * go01 + K(0.5) * gvz;
    gr[2] = K(0.5) * go02 + K(0.5) * gvy; gr[6] = K(0.5) * go02 - K(0.5) * gvy;
    gr[5] = K(0.5) * go12 - K(0.5) * gvx; gr[7] = K(0.5) * go12 + K(0.5) * gvx;
}

SO3_INLINE void FN(log_fwd_k)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2)
{
    (void)Bg;
    T r[9], w[3];
#define SO3_S(k) r[k] = A[k][j];
    SO3_EACH9(SO3_S)
#undef SO3_S
    FN(log1)(r, eps2, w);
    O[0][j] = w[0]; O[1][j] = w[1]; O[2][j] = w[2];
}

SO3_INLINE void FN(log_bwd_k)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2)
{
    T r[9], gw[3] = {Bg[0][j], Bg[1][j], Bg[2][j]}, gr[9];
#define SO3_S(k) r[k] = A[k][j];
    SO3_EACH9(SO3_S)
#undef SO3_S
    FN(log_bwd1)(r, gw, eps2, gr);
#define SO3_S(k) O[k][j] = gr[k];
    SO3_EACH9(SO3_S)
#undef SO3_S
}

#ifndef SO3_KERNELS_ONLY
SO3_RUNNER(FN(log_fwd_run), FN(log_fwd_k))
SO3_RUNNER(FN(log_bwd_run), FN(log_bwd_k))

void FN(so3_log_fwd)(const T *R, T *w, long n, int nt, double eps)
{
    FN(loop_t) c = {.a = R, .b = R, .out = w, .n = n, .na = 9, .nb = 0, .nout = 3, .flag = -1,
                    .kern = FN(log_fwd_run), .eps2 = (T)(eps * eps)};
    FN(loop)(&c, nt);
}
#endif /* SO3_KERNELS_ONLY */

/* Whether r is not a rotation within tol (tol2 = tol^2): e2 = ||R^T R - I||_F^2 (entries of
 * R^T R are the dot products of the columns (r0 r3 r6), (r1 r4 r7), (r2 r5 r8)) is not <= tol2
 * (which also holds for NaN and inf entries, whose e2 is NaN or inf), or det R < 0 (a
 * reflection). The same expressions, in the same order, as so3._rotation_flags (torch). */
static inline int FN(not_rotation)(const T *r, T tol2)
{
    T aa = r[0] * r[0] + r[3] * r[3] + r[6] * r[6] - K(1.0);
    T bb = r[1] * r[1] + r[4] * r[4] + r[7] * r[7] - K(1.0);
    T cc = r[2] * r[2] + r[5] * r[5] + r[8] * r[8] - K(1.0);
    T ab = r[0] * r[1] + r[3] * r[4] + r[6] * r[7];
    T ac = r[0] * r[2] + r[3] * r[5] + r[6] * r[8];
    T bc = r[1] * r[2] + r[4] * r[5] + r[7] * r[8];
    T e2 = aa * aa + bb * bb + cc * cc + K(2.0) * (ab * ab + ac * ac + bc * bc);
    T det = r[0] * (r[4] * r[8] - r[5] * r[7]) - r[1] * (r[3] * r[8] - r[5] * r[6])
          + r[2] * (r[3] * r[7] - r[4] * r[6]);
    return !(e2 <= tol2) | (det < K(0.0));
}

/* log_fwd_k plus the flag of not_rotation in row 3 of O (w is computed exactly as there) */
SO3_INLINE void FN(log_chk_k)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2, T tol2)
{
    (void)Bg;
    T r[9], w[3];
#define SO3_S(k) r[k] = A[k][j];
    SO3_EACH9(SO3_S)
#undef SO3_S
    FN(log1)(r, eps2, w);
    O[0][j] = w[0]; O[1][j] = w[1]; O[2][j] = w[2];
    O[3][j] = (T)FN(not_rotation)(r, tol2);  /* a cast, not a ?: (which stops the vectorizer) */
}

/* so3_log_fwd (same w, bitwise) that also validates: returns the number of matrices that are
 * not rotations within tol (Frobenius norm of R^T R - I, det < 0, NaN/inf) and writes the
 * smallest such index to *first (n if there is none). */
#ifndef SO3_KERNELS_ONLY
SO3_RUNNER_TOL(FN(log_chk_run), FN(log_chk_k))

long FN(so3_log_fwd_checked)(const T *R, T *w, long n, int nt, double eps, double tol, long *first_out)
{
    FN(loop_t) c = {.a = R, .b = R, .out = w, .n = n, .na = 9, .nb = 0, .nout = 3, .flag = 3,
                    .kern = FN(log_chk_run), .eps2 = (T)(eps * eps), .tol2 = (T)(tol * tol)};
    FN(loop)(&c, nt);
    *first_out = c.first;
    return c.nbad;
}

void FN(so3_log_bwd)(const T *R, const T *gw, T *gR, long n, int nt, double eps, long gs_elem, long gs_comp)
{
    FN(loop_t) c = {.a = R, .b = gw, .out = gR, .n = n, .b_es = gs_elem, .b_cs = gs_comp, .na = 9, .nb = 3,
                    .nout = 9, .flag = -1, .b_strided = 1,
                    .kern = FN(log_bwd_run), .eps2 = (T)(eps * eps)};
    FN(loop)(&c, nt);
}
#endif /* SO3_KERNELS_ONLY */

/* ---------------------------------------------------------------- sqrt */

/* _so3_formulas.sqrt: for tr R > 0 (angle below 120 degrees), with s = sqrt(1 + tr R),
 * sqrt(R) = ((1 + s) I + R + (R - R^T)/s) / (2 + s); otherwise exp(h), h = log(R)/2. */
SO3_INLINE void FN(sqrt_fwd_k)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2)
{
    (void)Bg;
    T r[9], w[3], e[9];
#define SO3_S(k) r[k] = A[k][j];
    SO3_EACH9(SO3_S)
#undef SO3_S
    T tr = r[0] + r[4] + r[8];
    int ok = tr > K(0.0);
    T s = SO3_SQRT(ok ? K(1.0) + tr : K(4.0));
    T inv_s = K(1.0) / s, den = K(1.0) / (K(2.0) + s), diag = K(1.0) + s;
    FN(log1)(r, eps2, w);
    FN(exp1)(K(0.5) * w[0], K(0.5) * w[1], K(0.5) * w[2], eps2, 1, e);
    O[0][j] = ok ? (diag + r[0]) * den : e[0];
    O[1][j] = ok ? (r[1] + (r[1] - r[3]) * inv_s) * den : e[1];
    O[2][j] = ok ? (r[2] + (r[2] - r[6]) * inv_s) * den : e[2];
    O[3][j] = ok ? (r[3] + (r[3] - r[1]) * inv_s) * den : e[3];
    O[4][j] = ok ? (diag + r[4]) * den : e[4];
    O[5][j] = ok ? (r[5] + (r[5] - r[7]) * inv_s) * den : e[5];
    O[6][j] = ok ? (r[6] + (r[6] - r[2]) * inv_s) * den : e[6];
    O[7][j] = ok ? (r[7] + (r[7] - r[5]) * inv_s) * den : e[7];
    O[8][j] = ok ? (diag + r[8]) * den : e[8];
}

SO3_INLINE void FN(sqrt_bwd_k)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2)
{
    T r[9], G[9], w[3], gh[3], ge[9];
#define SO3_S(k) r[k] = A[k][j]; G[k] = Bg[k][j];
    SO3_EACH9(SO3_S)
#undef SO3_S
    T tr = r[0] + r[4] + r[8];
    int ok = tr > K(0.0);
    /* tr R <= 0: through exp(h), h = log(R)/2 */
    FN(log1)(r, eps2, w);
    FN(exp_bwd1)(K(0.5) * w[0], K(0.5) * w[1], K(0.5) * w[2], G, eps2, 1, gh);
    gh[0] = K(0.5) * gh[0]; gh[1] = K(0.5) * gh[1]; gh[2] = K(0.5) * gh[2];
    FN(log_bwd1)(r, gh, eps2, ge);
    /* tr R > 0: out = P den, P_ii = diag + r_ii, P_ij = r_ij + (r_ij - r_ji) inv_s */
    T s = SO3_SQRT(ok ? K(1.0) + tr : K(4.0));
    T inv_s = K(1.0) / s, den = K(1.0) / (K(2.0) + s), diag = K(1.0) + s;
    T p01 = r[1] - r[3], p02 = r[2] - r[6], p12 = r[5] - r[7];  /* r_ij - r_ji, i < j */
    T gden = G[0] * (diag + r[0]) + G[1] * (r[1] + p01 * inv_s) + G[2] * (r[2] + p02 * inv_s)
           + G[3] * (r[3] - p01 * inv_s) + G[4] * (diag + r[4]) + G[5] * (r[5] + p12 * inv_s)
           + G[6] * (r[6] - p02 * inv_s) + G[7] * (r[7] - p12 * inv_s) + G[8] * (diag + r[8]);
    T g[9];
#define SO3_S(k) g[k] = G[k] * den;  /* dL/dP */
    SO3_EACH9(SO3_S)
#undef SO3_S
    T gdiag = g[0] + g[4] + g[8];
    T ginv = (g[1] - g[3]) * p01 + (g[2] - g[6]) * p02 + (g[5] - g[7]) * p12;
    T a = K(1.0) + inv_s;
    /* den = 1/(2 + s), diag = 1 + s, inv_s = 1/s, s = sqrt(1 + tr) */
    T gs = -gden * den * den + gdiag - ginv * inv_s * inv_s;
    T gtr = gs / (K(2.0) * s);
    O[0][j] = ok ? g[0] + gtr : ge[0];
    O[4][j] = ok ? g[4] + gtr : ge[4];
    O[8][j] = ok ? g[8] + gtr : ge[8];
    O[1][j] = ok ? g[1] * a - g[3] * inv_s : ge[1];
    O[3][j] = ok ? g[3] * a - g[1] * inv_s : ge[3];
    O[2][j] = ok ? g[2] * a - g[6] * inv_s : ge[2];
    O[6][j] = ok ? g[6] * a - g[2] * inv_s : ge[6];
    O[5][j] = ok ? g[5] * a - g[7] * inv_s : ge[5];
    O[7][j] = ok ? g[7] * a - g[5] * inv_s : ge[7];
}

/* Blocks whose every element has tr R > 0 (the usual case: angles below 120 degrees) run only
 * the half-angle branch: sqrt_fwd_k / sqrt_bwd_k select it for every element there, and the
 * kernels below are its expressions, unchanged (so the same values, bitwise), without the
 * log / exp branch (its trigonometric calls are most of the cost). The test is the same sum
 * in the same order as `ok` in the kernels (NaN traces fail it). */
#define SO3_POS_TRACE(A_, j) ((A_)[0][j] + (A_)[4][j] + (A_)[8][j] > K(0.0))

SO3_INLINE void FN(sqrt_fwd_pos_k)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2)
{
    (void)Bg; (void)eps2;
    T r[9];
#define SO3_S(k) r[k] = A[k][j];
    SO3_EACH9(SO3_S)
#undef SO3_S
    T tr = r[0] + r[4] + r[8];
    T s = SO3_SQRT(K(1.0) + tr);
    T inv_s = K(1.0) / s, den = K(1.0) / (K(2.0) + s), diag = K(1.0) + s;
    O[0][j] = (diag + r[0]) * den;
    O[1][j] = (r[1] + (r[1] - r[3]) * inv_s) * den;
    O[2][j] = (r[2] + (r[2] - r[6]) * inv_s) * den;
    O[3][j] = (r[3] + (r[3] - r[1]) * inv_s) * den;
    O[4][j] = (diag + r[4]) * den;
    O[5][j] = (r[5] + (r[5] - r[7]) * inv_s) * den;
    O[6][j] = (r[6] + (r[6] - r[2]) * inv_s) * den;
    O[7][j] = (r[7] + (r[7] - r[5]) * inv_s) * den;
    O[8][j] = (diag + r[8]) * den;
}

SO3_INLINE void FN(sqrt_bwd_pos_k)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int j, T eps2)
{
    (void)eps2;
    T r[9], G[9];
#define SO3_S(k) r[k] = A[k][j]; G[k] = Bg[k][j];
    SO3_EACH9(SO3_S)
#undef SO3_S
    T tr = r[0] + r[4] + r[8];
    T s = SO3_SQRT(K(1.0) + tr);
    T inv_s = K(1.0) / s, den = K(1.0) / (K(2.0) + s), diag = K(1.0) + s;
    T p01 = r[1] - r[3], p02 = r[2] - r[6], p12 = r[5] - r[7];
    T gden = G[0] * (diag + r[0]) + G[1] * (r[1] + p01 * inv_s) + G[2] * (r[2] + p02 * inv_s)
           + G[3] * (r[3] - p01 * inv_s) + G[4] * (diag + r[4]) + G[5] * (r[5] + p12 * inv_s)
           + G[6] * (r[6] - p02 * inv_s) + G[7] * (r[7] - p12 * inv_s) + G[8] * (diag + r[8]);
    T g[9];
#define SO3_S(k) g[k] = G[k] * den;
    SO3_EACH9(SO3_S)
#undef SO3_S
    T gdiag = g[0] + g[4] + g[8];
    T ginv = (g[1] - g[3]) * p01 + (g[2] - g[6]) * p02 + (g[5] - g[7]) * p12;
    T a = K(1.0) + inv_s;
    T gs = -gden * den * den + gdiag - ginv * inv_s * inv_s;
    T gtr = gs / (K(2.0) * s);
    O[0][j] = g[0] + gtr;
    O[4][j] = g[4] + gtr;
    O[8][j] = g[8] + gtr;
    O[1][j] = g[1] * a - g[3] * inv_s;
    O[3][j] = g[3] * a - g[1] * inv_s;
    O[2][j] = g[2] * a - g[6] * inv_s;
    O[6][j] = g[6] * a - g[2] * inv_s;
    O[5][j] = g[5] * a - g[7] * inv_s;
    O[7][j] = g[7] * a - g[5] * inv_s;
}

SO3_RUNNER(FN(sqrt_fwd_run), FN(sqrt_fwd_k))
SO3_RUNNER(FN(sqrt_fwd_pos_run), FN(sqrt_fwd_pos_k))
SO3_RUNNER(FN(sqrt_bwd_run), FN(sqrt_bwd_k))
SO3_RUNNER(FN(sqrt_bwd_pos_run), FN(sqrt_bwd_pos_k))

/* whether every matrix of the block has tr R > 0 (the runners ..._pos_run apply) */
static int FN(sqrt_block_pos)(FN(blk_t) *A_, int m)
{
    int fast_ = 1;
    for (int j = 0; j < m; ++j)
        fast_ &= SO3_POS_TRACE(A_, j);
    return fast_;
}

#ifndef SO3_KERNELS_ONLY
void FN(so3_sqrt_fwd)(const T *R, T *S, long n, int nt, double eps)
{
    FN(loop_t) c = {.a = R, .b = R, .out = S, .n = n, .na = 9, .nb = 0, .nout = 9, .flag = -1,
                    .kern = FN(sqrt_fwd_run), .fast = FN(sqrt_fwd_pos_run),
                    .fast_if = FN(sqrt_block_pos), .eps2 = (T)(eps * eps)};
    FN(loop)(&c, nt);
}

void FN(so3_sqrt_bwd)(const T *R, const T *gS, T *gR, long n, int nt, double eps, long gs_elem, long gs_comp)
{
    FN(loop_t) c = {.a = R, .b = gS, .out = gR, .n = n, .b_es = gs_elem, .b_cs = gs_comp, .na = 9, .nb = 9,
                    .nout = 9, .flag = -1, .b_strided = 1,
                    .kern = FN(sqrt_bwd_run), .fast = FN(sqrt_bwd_pos_run),
                    .fast_if = FN(sqrt_block_pos), .eps2 = (T)(eps * eps)};
    FN(loop)(&c, nt);
}
#else
/* For the including file: sqrt (and its backward for the gradient Bg) of the m <= SO3_B
 * matrices of a component-major block A, into O; the same runners, chosen the same way, as
 * so3_sqrt_fwd / so3_sqrt_bwd (so the same values, bitwise). */
static inline void FN(sqrt_fwd_block)(FN(blk_t) *A, FN(blk_t) *O, int m, T eps2)
{
    (FN(sqrt_block_pos)(A, m) ? FN(sqrt_fwd_pos_run) : FN(sqrt_fwd_run))(A, A, O, m, eps2, K(0.0));
}

static inline void FN(sqrt_bwd_block)(FN(blk_t) *A, FN(blk_t) *Bg, FN(blk_t) *O, int m, T eps2)
{
    (FN(sqrt_block_pos)(A, m) ? FN(sqrt_bwd_pos_run) : FN(sqrt_bwd_run))(A, Bg, O, m, eps2, K(0.0));
}
#endif /* SO3_KERNELS_ONLY */

#undef SO3_POS_TRACE

#ifndef SO3_KERNELS_ONLY
/* The written-out sin, cos (|t| <= SO3_TRIG_MAX) and atan2 over arrays, for the tests of their
 * accuracy: so3_sincos_SUF(t, s, c, n), so3_atan2_SUF(y, x, out, n). */
void FN(so3_sincos)(const T *t, T *s, T *c, long n)
{
    _Pragma("omp simd")
    for (long i = 0; i < n; ++i)
        FN(sincos)(t[i], &s[i], &c[i]);
}

void FN(so3_atan2)(const T *y, const T *x, T *out, long n)
{
    _Pragma("omp simd")
    for (long i = 0; i < n; ++i)
        out[i] = FN(atan2v)(y[i], x[i]);
}
#endif /* SO3_KERNELS_ONLY */

#undef SO3_TRIG_MAX
#undef T
#undef FN
#undef K

#endif /* SO3_T */
