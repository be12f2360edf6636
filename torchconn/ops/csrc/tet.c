/* The averaged d∇ Alt d∇ Alt θ̃ tet kernel (torchconn.ops.tet): forward and backward, float32/64.
 *
 * Layout (row-major, contiguous; leading batch dims flattened to nb and looped here):
 *   rot   (nb, E, 9)     R_ij of the canonical edges
 *   theta (nb, E, 2, 3)  [e, 0] = θ̃_ij, [e, 1] = θ̃_ji
 *   ridx  (T, 6) int64   2 e + (tet traverses edge e against its orientation), pairs ab ac ad bc bd cd
 *   tidx  (T, 7) int64   2 e + dir of θ̃_ba θ̃_ca θ̃_da θ̃_cb θ̃_db θ̃_dc θ̃_cd
 *   out   (nb, T, 3)
 * Backward: gin (nb, T, 3) -> grot (nb, E, 9), gtheta (nb, E, 2, 3) (overwritten).
 *
 * Lanes: tets are processed in blocks of LANES. A block's rotations and θ̃ are gathered into
 * component-major arrays (R[p][q][lane], oriented: R_e or R_e^T by the low bit of ridx), the
 * formula then runs as one loop over the lanes that the compiler vectorizes (the same
 * arithmetic per tet as the scalar formula, in the same order; -std=c99 forbids FMA
 * contraction), and the results go back per tet. With AVX-512 (float32) a block is gathered
 * with masked row loads and 16 x 16 register transposes instead of scalar copies (the same
 * values; 1M tets, one thread: backward 131 -> 124 ms, forward 46 -> 43 ms: what remains is
 * waiting for memory, not instructions).
 *
 * The forward writes its own row per tet (parallel over blocks). The backward scatters into
 * the edges race-free without atomics or per-thread copies: the tets are processed in chunks
 * (order[chunk_start[k] .. chunk_start[k+1]]), and chunks are grouped in colors (chunks
 * color_start[c] .. color_start[c+1]) such that no two chunks of one color share an edge (built
 * once per mesh by torchconn.ops.tet._schedule); the chunks of one color run in parallel, each
 * sequentially (its blocks in order, the lanes of a block scattered in order: the sum at every
 * edge is in a fixed order, whatever the number of threads), and the colors one after the other.
 *
 * The √R variant (tet_dds_*) forms θ̃_ij = H_e v_e, θ̃_ji = -H_e^T v_e once per *edge* in a
 * first pass (parallel over edges) into a scratch it maps itself (tc_scratch, pool.c), then runs the
 * kernels above; its backward turns the gradient of every directed θ̃ into those of H and v in
 * a last pass over edges. The fused variant (tet_ddr_*) also forms H = √R_e in those passes.
 *
 * Exported (T_ = float / double, SUF = f32 / f64):
 *   tet_dd_fwd_SUF(rot, theta, ridx, tidx, out, nb, E, T, threads)
 *   tet_dd_bwd_SUF(rot, theta, gin, ridx, tidx, order, chunk_start, color_start, n_colors,
 *                  grot, gtheta, nb, E, T, threads)
 *   int tet_dds_fwd_SUF(rot, half, vec, ridx, tidx, out, nb, E, T, threads)
 *   int tet_dds_bwd_SUF(rot, half, vec, gin, ridx, tidx, order, chunk_start, color_start, n_colors,
 *                       grot, ghalf, gvec, nb, E, T, threads)
 *   int tet_ddr_fwd_SUF(rot, vec, ridx, tidx, out, nb, E, T, threads, eps)
 *   int tet_ddr_bwd_SUF(rot, vec, gin, ridx, tidx, order, chunk_start, color_start, n_colors,
 *                       grot, gvec, nb, E, T, threads, eps)
 *   int tet_ddf_fwd_SUF(rot, frames, vec, edges, ridx, tidx, out, nb, E, V, T, threads, eps)
 *   int tet_ddf_bwd_SUF(rot, frames, vec, edges, gin, ridx, tidx, order, chunk_start, color_start,
 *                       n_colors, grot, gframes, gvec, nb, E, V, T, threads, eps)
 *   int tet_ddf_sqn_SUF(rot, frames, vec, edges, w, ridx, tidx, order, chunk_start, color_start,
 *                       n_colors, value, grot, gframes, nb, E, V, T, threads, eps, grad)
 * (tet_ddr_*: √R formed in the kernel as well, eps the so3 small-angle threshold; tet_ddf_*: the
 * solder form in a frame field, θ̃'_ij = F_i^T √(F_i R F_j^T) v, formed in the kernel; tet_ddf_sqn_*:
 * the value sum_t w_t |dd_t|^2 of tet_ddf per item (double) and, with grad, its gradient in one sweep)
 * (the √R variants return 0, or -1 when their scratch cannot be mapped; in tet_dds_bwd the θ̃
 * of pass 1 live in ghalf (its first 6E entries per item) until the last pass overwrites it).
 */
#ifndef TET_T

#define _DEFAULT_SOURCE /* mmap's MAP_ANONYMOUS, madvise (tc_scratch of pool.c) */
#include <stdint.h>
#include <string.h>

/* the SO(3) square root and its backward (element kernels and block helpers of so3.c, the one
 * home of those formulas) for the fused tet_ddr_* kernels */
#define SO3_KERNELS_ONLY
#include "so3.c"
#undef SO3_KERNELS_ONLY

#define TET_CAT_(a, b) a##b
#define TET_CAT(a, b) TET_CAT_(a, b)
/* tets per lane block: one 512-bit register of float32 lanes */
#define LANES 16
/* loops over fewer edges than this run on the calling thread (no pool wake-up) */
#define TET_PAR_MIN 32768L
/* tet loops over fewer tets than this too */
#define TET_PAR_MIN_TETS 4096L
/* lane blocks (of LANES tets) / edges / SO3_B-edge blocks per task of the pool */
#define TET_TASK_BLOCKS 16L
#define TET_TASK_EDGES 4096L
#define TET_TASK_SO3 16L

#define TC_POOL_CLIENT
#define TC_POOL_SCRATCH /* tc_scratch */
#include "pool.c" /* tc_parallel */

#if defined(__AVX512F__)
#include <immintrin.h>
/* r[i] <- column i of the 16 x 16 matrix with rows r[0..15] */
static inline void tet_transpose16(__m512 *r)
{
    __m512 t[16];
    for (int i = 0; i < 8; i++) {
        t[2 * i] = _mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
        t[2 * i + 1] = _mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
    }
    for (int i = 0; i < 4; i++) {
        const __m512d a = _mm512_castps_pd(t[4 * i]), b = _mm512_castps_pd(t[4 * i + 1]);
        const __m512d c = _mm512_castps_pd(t[4 * i + 2]), d = _mm512_castps_pd(t[4 * i + 3]);
        r[4 * i] = _mm512_castpd_ps(_mm512_unpacklo_pd(a, c));
        r[4 * i + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(a, c));
        r[4 * i + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(b, d));
        r[4 * i + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(b, d));
    }
    for (int i = 0; i < 2; i++)
        for (int k = 0; k < 4; k++) {
            t[8 * i + k] = _mm512_shuffle_f32x4(r[8 * i + k], r[8 * i + 4 + k], 0x88);
            t[8 * i + 4 + k] = _mm512_shuffle_f32x4(r[8 * i + k], r[8 * i + 4 + k], 0xdd);
        }
    for (int k = 0; k < 8; k++) {
        r[k] = _mm512_shuffle_f32x4(t[k], t[8 + k], 0x88);
        r[8 + k] = _mm512_shuffle_f32x4(t[k], t[8 + k], 0xdd);
    }
}
#define TET_AVX512_F32 1
#endif

#define TET_T float
#define TET_SUF _f32
#define TET_IS_F32 1
#include "tet.c" /* this file, again (quoted includes resolve next to it) */
#undef TET_T
#undef TET_SUF
#undef TET_IS_F32

#define TET_T double
#define TET_SUF _f64
#include "tet.c"

#else /* ------------------------------------------------------------- one dtype */

#define T_ TET_T
#define FN(name) TET_CAT(name, TET_SUF)
#define S6 ((T_)(1.0 / 6.0))
#define S3 ((T_)(1.0 / 3.0))
#define HALF ((T_)0.5)

/* component-major block of LANES tets */
typedef struct {
    T_ R[6][9][LANES]; /* oriented rotations ab ac ad bc bd cd */
    T_ t[7][3][LANES]; /* θ̃ ba ca da cb db dc cd */
    T_ g[3][LANES];    /* forward: the output; backward: its gradient */
} FN(block);

typedef struct {
    T_ R[6][9][LANES];
    T_ t[7][3][LANES];
} FN(gblock);

/* lane l of the block: tet k */
static inline void FN(gather)(FN(block) *b, int l, const T_ *rot, const T_ *th, const int64_t *ri,
                              const int64_t *ti)
{
    for (int p = 0; p < 6; p++) {
        const T_ *s = rot + 9 * (ri[p] >> 1);
        if (ri[p] & 1) {
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++)
                    b->R[p][3 * i + j][l] = s[3 * j + i];
        } else {
            for (int q = 0; q < 9; q++)
                b->R[p][q][l] = s[q];
        }
    }
    for (int k = 0; k < 7; k++) {
        const T_ *s = th + 3 * ti[k];
        b->t[k][0][l] = s[0]; b->t[k][1][l] = s[1]; b->t[k][2][l] = s[2];
    }
}

/* unused lanes of a partial block: finite values (their results are not read) */
static inline void FN(pad)(FN(block) *b, int n)
{
    for (int l = n; l < LANES; l++) {
        for (int p = 0; p < 6; p++)
            for (int q = 0; q < 9; q++)
                b->R[p][q][l] = 0;
        for (int k = 0; k < 7; k++)
            for (int i = 0; i < 3; i++)
                b->t[k][i][l] = 0;
        for (int i = 0; i < 3; i++)
            b->g[i][l] = 0;
    }
}

/* the whole block: lane l <- tet with rows ris[l] (ridx) and tis[l] (tidx), lanes >= n copies of
 * lane 0 (finite values, results unused) */
static inline void FN(gather_block)(FN(block) *b, int n, const T_ *rot, const T_ *th,
                                    const int64_t *const *ris, const int64_t *const *tis)
{
#if defined(TET_AVX512_F32) && defined(TET_IS_F32)
    const __m512i tq = _mm512_setr_epi32(0, 3, 6, 1, 4, 7, 2, 5, 8, 9, 10, 11, 12, 13, 14, 15);
    __m512 r[16];
    for (int p = 0; p < 6; p++) {
        for (int l = 0; l < LANES; l++) {
            const int64_t ix = ris[l < n ? l : 0][p];
            const __m512 x = _mm512_maskz_loadu_ps(0x1FF, rot + 9 * (ix >> 1));
            r[l] = _mm512_mask_permutexvar_ps(x, (__mmask16)(-(int)(ix & 1)) & 0x1FF, tq, x);
        }
        tet_transpose16(r);
        for (int q = 0; q < 9; q++)
            _mm512_storeu_ps(b->R[p][q], r[q]);
    }
    for (int l = 0; l < LANES; l++) {
        const int64_t *ti = tis[l < n ? l : 0];
        __m512 x = _mm512_setzero_ps();
        for (int k = 0; k < 5; k++)
            x = _mm512_mask_expandloadu_ps(x, (__mmask16)(0x7 << (3 * k)), th + 3 * ti[k]);
        r[l] = x;
    }
    tet_transpose16(r);
    for (int k = 0; k < 5; k++)
        for (int i = 0; i < 3; i++)
            _mm512_storeu_ps(b->t[k][i], r[3 * k + i]);
    for (int l = 0; l < LANES; l++) {
        const int64_t *ti = tis[l < n ? l : 0];
        __m512 x = _mm512_maskz_expandloadu_ps(0x7, th + 3 * ti[5]);
        r[l] = _mm512_mask_expandloadu_ps(x, 0x38, th + 3 * ti[6]);
    }
    tet_transpose16(r);
    for (int k = 5; k < 7; k++)
        for (int i = 0; i < 3; i++)
            _mm512_storeu_ps(b->t[k][i], r[3 * (k - 5) + i]);
#else
    for (int l = 0; l < n; l++)
        FN(gather)(b, l, rot, th, ris[l], tis[l]);
    FN(pad)(b, n);
#endif
}

/* per-lane access: R_p entry q, θ̃_k entry i */
#define RL(p, q) (b->R[p][q][l])
#define MV_L(y, p, x) do { for (int _i = 0; _i < 3; _i++) \
    (y)[_i] = RL(p, 3 * _i) * (x)[0] + RL(p, 3 * _i + 1) * (x)[1] + RL(p, 3 * _i + 2) * (x)[2]; } while (0)
#define MTV_L(y, p, x) do { for (int _i = 0; _i < 3; _i++) \
    (y)[_i] = RL(p, _i) * (x)[0] + RL(p, 3 + _i) * (x)[1] + RL(p, 6 + _i) * (x)[2]; } while (0)

/* the regrouped Ch. 5 formula (torchconn.ops.tet.tet_dd_from_rotations), lane l; intermediates
 * y_c, y_d, x_b, x_c, x_d */
#define FORWARD_LANE                                                                             \
    T_ t[7][3];                                                                                  \
    for (int k = 0; k < 7; k++)                                                                  \
        for (int i = 0; i < 3; i++)                                                              \
            t[k][i] = b->t[k][i][l];                                                             \
    T_ pcd0[3], pcd1[3], pdc0[3], pdc1[3], pcb[3], pdb[3], yc[3], yd[3], xb[3], xc[3], xd[3];   \
    T_ u_[3], v_[3];                                                                             \
    MV_L(pcd0, 5, t[4]); MV_L(pcd1, 5, t[2]);                                                    \
    MTV_L(pdc0, 5, t[3]); MTV_L(pdc1, 5, t[1]);                                                  \
    MTV_L(pcb, 3, t[0]); MTV_L(pdb, 4, t[0]);                                                    \
    for (int i = 0; i < 3; i++) {                                                                \
        yc[i] = S6 * (pcd0[i] - t[1][i]) - S3 * t[3][i] + HALF * t[6][i];                        \
        yd[i] = S6 * (t[2][i] - pdc0[i]) + S3 * t[4][i] - HALF * t[5][i];                        \
        xc[i] = S6 * (pcb[i] - pcd1[i]) + HALF * (t[3][i] - t[6][i]);                            \
        xd[i] = S6 * (pdc1[i] - pdb[i]) - HALF * (t[4][i] - t[5][i]);                            \
    }                                                                                            \
    MV_L(u_, 3, yc); MV_L(v_, 4, yd);                                                            \
    for (int i = 0; i < 3; i++) xb[i] = u_[i] + v_[i];

/* not inlined: inlined into the chunk loops, gcc 12 no longer vectorizes the lane loop */
__attribute__((noinline)) static void FN(block_fwd)(FN(block) *b)
{
#pragma omp simd
    for (int l = 0; l < LANES; l++) {
        FORWARD_LANE
        for (int i = 0; i < 3; i++)
            b->g[i][l] = RL(0, 3 * i) * xb[0] + RL(0, 3 * i + 1) * xb[1] + RL(0, 3 * i + 2) * xb[2]
                       + RL(1, 3 * i) * xc[0] + RL(1, 3 * i + 1) * xc[1] + RL(1, 3 * i + 2) * xc[2]
                       + RL(2, 3 * i) * xd[0] + RL(2, 3 * i + 1) * xd[1] + RL(2, 3 * i + 2) * xd[2];
    }
}

/* reverse of block_fwd (the forward recomputed): gradients of the 6 oriented R_p and 7 θ̃ */
__attribute__((noinline)) static void FN(block_bwd)(FN(block) *b, FN(gblock) *o)
{
#pragma omp simd
    for (int l = 0; l < LANES; l++) {
        FORWARD_LANE
        T_ g[3] = {b->g[0][l], b->g[1][l], b->g[2][l]};
        T_ gxb[3], gxc[3], gxd[3], gyc[3], gyd[3];
        MTV_L(gxb, 0, g); MTV_L(gxc, 1, g); MTV_L(gxd, 2, g);
        MTV_L(gyc, 3, gxb); MTV_L(gyd, 4, gxb);
        T_ gpcd0[3], gpdc0[3], gpcb[3], gpcd1[3], gpdc1[3], gpdb[3];
        for (int i = 0; i < 3; i++) {
            gpcd0[i] = S6 * gyc[i]; gpdc0[i] = -S6 * gyd[i];
            gpcb[i] = S6 * gxc[i]; gpcd1[i] = -S6 * gxc[i];
            gpdc1[i] = S6 * gxd[i]; gpdb[i] = -S6 * gxd[i];
        }
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) {
                const int q = 3 * i + j;
                o->R[0][q][l] = g[i] * xb[j];
                o->R[1][q][l] = g[i] * xc[j];
                o->R[2][q][l] = g[i] * xd[j];
                o->R[3][q][l] = gxb[i] * yc[j] + t[0][i] * gpcb[j];
                o->R[4][q][l] = gxb[i] * yd[j] + t[0][i] * gpdb[j];
                o->R[5][q][l] = gpcd0[i] * t[4][j] + gpcd1[i] * t[2][j] + t[3][i] * gpdc0[j]
                              + t[1][i] * gpdc1[j];
            }
        MV_L(u_, 3, gpcb); MV_L(v_, 4, gpdb);
        for (int i = 0; i < 3; i++) o->t[0][i][l] = u_[i] + v_[i];
        MV_L(u_, 5, gpdc1);
        for (int i = 0; i < 3; i++) o->t[1][i][l] = u_[i] - S6 * gyc[i];
        MTV_L(u_, 5, gpcd1);
        for (int i = 0; i < 3; i++) o->t[2][i][l] = u_[i] + S6 * gyd[i];
        MV_L(u_, 5, gpdc0);
        for (int i = 0; i < 3; i++) o->t[3][i][l] = u_[i] - S3 * gyc[i] + HALF * gxc[i];
        MTV_L(u_, 5, gpcd0);
        for (int i = 0; i < 3; i++) o->t[4][i][l] = u_[i] + S3 * gyd[i] - HALF * gxd[i];
        for (int i = 0; i < 3; i++) {
            o->t[5][i][l] = HALF * (gxd[i] - gyd[i]);
            o->t[6][i][l] = HALF * (gyc[i] - gxc[i]);
        }
    }
}

/* lane l's gradients added into the edges of its tet */
static inline void FN(scatter)(const FN(gblock) *o, int l, const int64_t *ri, const int64_t *ti, T_ *grot,
                               T_ *gth)
{
    for (int p = 0; p < 6; p++) {
        T_ *d = grot + 9 * (ri[p] >> 1);
        if (ri[p] & 1) {
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++)
                    d[3 * j + i] += o->R[p][3 * i + j][l];
        } else {
            for (int q = 0; q < 9; q++)
                d[q] += o->R[p][q][l];
        }
    }
    for (int k = 0; k < 7; k++) {
        T_ *d = gth + 3 * ti[k];
        d[0] += o->t[k][0][l]; d[1] += o->t[k][1][l]; d[2] += o->t[k][2][l];
    }
}

/* the arguments of the loops below over one batch item (tasks: see each loop) */
typedef struct {
    const T_ *rot, *th, *half, *vec, *gin;
    const int64_t *ridx, *tidx, *order, *chunk_start;
    T_ *out, *grot, *gth, *ghalf, *gvec;
    int64_t E, T, c0, nc, th_stride;
    T_ eps2;
} FN(args_t);

/* task: TET_TASK_BLOCKS lane blocks of tets */
static void FN(fwd_task)(void *vc, long task)
{
    const FN(args_t) *c = (const FN(args_t) *)vc;
    const int64_t T = c->T, nblk = (T + LANES - 1) / LANES;
    const int64_t w1 = (task + 1) * TET_TASK_BLOCKS < nblk ? (task + 1) * TET_TASK_BLOCKS : nblk;
    for (int64_t w = task * TET_TASK_BLOCKS; w < w1; w++) {
        FN(block) b;
        const int64_t k0 = w * LANES;
        const int n = (int)(T - k0 < LANES ? T - k0 : LANES);
        const int64_t *ris[LANES], *tis[LANES];
        for (int l = 0; l < n; l++) {
            ris[l] = c->ridx + 6 * (k0 + l);
            tis[l] = c->tidx + 7 * (k0 + l);
        }
        FN(gather_block)(&b, n, c->rot, c->th, ris, tis);
        FN(block_fwd)(&b);
        for (int l = 0; l < n; l++)
            for (int i = 0; i < 3; i++)
                c->out[3 * (k0 + l) + i] = b.g[i][l];
    }
}

void FN(tet_dd_fwd)(const T_ *rot, const T_ *th, const int64_t *ridx, const int64_t *tidx, T_ *out,
                    int64_t nb, int64_t E, int64_t T, int threads)
{
    const int64_t nblk = (T + LANES - 1) / LANES;
    for (int64_t bi = 0; bi < nb; bi++) {
        FN(args_t) c = {.rot = rot + bi * 9 * E, .th = th + bi * 6 * E, .ridx = ridx, .tidx = tidx,
                        .out = out + bi * 3 * T, .E = E, .T = T};
        tc_parallel(tc_tasks(nblk, TET_TASK_BLOCKS), T >= TET_PAR_MIN_TETS ? threads : 1, FN(fwd_task), &c);
    }
}

/* zero n entries, in parallel when large (the first touch of fresh output pages); a task
 * zeroes TET_ZERO_STEP entries */
#define TET_ZERO_STEP (1L << 16)
typedef struct {
    T_ *x;
    int64_t n;
} FN(zero_t);

static void FN(zero_task)(void *vc, long task)
{
    const FN(zero_t) *c = (const FN(zero_t) *)vc;
    const int64_t s = task * TET_ZERO_STEP;
    memset(c->x + s, 0, sizeof(T_) * (size_t)(c->n - s < TET_ZERO_STEP ? c->n - s : TET_ZERO_STEP));
}

static void FN(zero)(T_ *x, int64_t n, int threads)
{
    FN(zero_t) c = {x, n};
    tc_parallel(tc_tasks(n, TET_ZERO_STEP), n >= 16 * TET_ZERO_STEP ? threads : 1, FN(zero_task), &c);
}

/* prefetch the rows of tets order[s .. min(s + LANES, end)) (read: rotations, θ̃; added to: grot,
 * gth) while the current block computes: the gathers and scatters, not the arithmetic, bound
 * the backward (at 1M tets, one thread: 119 -> 110 ms; as a call that gcc does not inline, the
 * gain is lost) */
__attribute__((always_inline)) static inline void FN(prefetch)(
    const T_ *rot, const T_ *th, T_ *grot, T_ *gth, const int64_t *ridx, const int64_t *tidx,
    const int64_t *order, int64_t s, int64_t end)
{
    for (int64_t i = s; i < end && i < s + LANES; i++) {
        const int64_t k = order[i];
        const int64_t *ri = ridx + 6 * k, *ti = tidx + 7 * k;
        for (int p = 0; p < 6; p++) {
            __builtin_prefetch(rot + 9 * (ri[p] >> 1), 0, 3);
            __builtin_prefetch(grot + 9 * (ri[p] >> 1), 1, 3);
        }
        for (int q = 0; q < 7; q++) {
            __builtin_prefetch(th + 3 * ti[q], 0, 3);
            __builtin_prefetch(gth + 3 * ti[q], 1, 3);
        }
    }
}

/* task w: chunk c0 + w % nc of one color for batch item w / nc: grot (nb, E, 9), gth (nb, E, 2,
 * 3) accumulated (zeroed by the caller); item bi's θ̃ at th + bi * th_stride. The chunks of one
 * color touch disjoint edges within an item, the items disjoint memory: tasks never race, and
 * each edge's sum is in a fixed order */
static void FN(bwd_chunk_task)(void *vc, long w)
{
    const FN(args_t) *c = (const FN(args_t) *)vc;
    const int64_t E = c->E, T = c->T;
    const int64_t bi = w / c->nc, ch = c->c0 + w % c->nc;
    const int64_t *ridx = c->ridx, *tidx = c->tidx, *order = c->order, *chunk_start = c->chunk_start;
    const T_ *r = c->rot + bi * 9 * E, *t = c->th + bi * c->th_stride, *g = c->gin + bi * 3 * T;
    T_ *gr = c->grot + bi * 9 * E, *gt = c->gth + bi * 6 * E;
    FN(block) b;
    FN(gblock) o;
    for (int64_t s0 = chunk_start[ch]; s0 < chunk_start[ch + 1]; s0 += LANES) {
        const int n = (int)(chunk_start[ch + 1] - s0 < LANES ? chunk_start[ch + 1] - s0 : LANES);
        const int64_t *ris[LANES], *tis[LANES];
        for (int l = 0; l < LANES; l++) {
            const int64_t k = order[s0 + (l < n ? l : 0)];
            ris[l] = ridx + 6 * k;
            tis[l] = tidx + 7 * k;
            b.g[0][l] = l < n ? g[3 * k] : 0;
            b.g[1][l] = l < n ? g[3 * k + 1] : 0;
            b.g[2][l] = l < n ? g[3 * k + 2] : 0;
        }
        FN(gather_block)(&b, n, r, t, ris, tis);
        FN(prefetch)(r, t, gr, gt, ridx, tidx, order, s0 + LANES, chunk_start[ch + 1]);
        FN(block_bwd)(&b, &o);
        for (int l = 0; l < n; l++) {
            const int64_t k = order[s0 + l];
            FN(scatter)(&o, l, ridx + 6 * k, tidx + 7 * k, gr, gt);
        }
    }
}

/* the chunks of one color, for every batch item (see bwd_chunk_task) */
static void FN(bwd_item_chunks)(const T_ *rb, const T_ *tb, const T_ *gb, const int64_t *ridx,
                                const int64_t *tidx, const int64_t *order, const int64_t *chunk_start,
                                int64_t c0, int64_t nc, int64_t nb, int64_t E, int64_t T,
                                int64_t th_stride, T_ *grot, T_ *gth, int threads)
{
    FN(args_t) c = {.rot = rb, .th = tb, .gin = gb, .ridx = ridx, .tidx = tidx, .order = order,
                    .chunk_start = chunk_start, .grot = grot, .gth = gth, .E = E, .T = T, .c0 = c0,
                    .nc = nc, .th_stride = th_stride};
    const int64_t tets = nc > 0 ? chunk_start[c0 + nc] - chunk_start[c0] : 0;
    tc_parallel(nb * nc, tets * nb >= TET_PAR_MIN_TETS ? threads : 1, FN(bwd_chunk_task), &c);
}

void FN(tet_dd_bwd)(const T_ *rot, const T_ *th, const T_ *gin, const int64_t *ridx,
                    const int64_t *tidx, const int64_t *order, const int64_t *chunk_start,
                    const int64_t *color_start, int64_t n_colors, T_ *grot, T_ *gth,
                    int64_t nb, int64_t E, int64_t T, int threads)
{
    FN(zero)(grot, 9 * E * nb, threads);
    FN(zero)(gth, 6 * E * nb, threads);
    for (int64_t c = 0; c < n_colors; c++)
        FN(bwd_item_chunks)(rot, th, gin, ridx, tidx, order, chunk_start, color_start[c],
                            color_start[c + 1] - color_start[c], nb, E, T, 6 * E, grot, gth,
                            threads);
}

/* ---- θ̃ formed from the half transports: θ̃_ij = H_e v_e (dir 0), θ̃_ji = -H_e^T v_e (dir 1),
 * half (nb, E, 9), vec (E, 3) shared by the batch; ghalf (nb, E, 9), gvec (nb, E, 3) per item
 * (summed by the caller) */

/* θ̃ (nb, E, 2, 3) of every edge, one pass over the edges; task: TET_TASK_EDGES edges */
static void FN(theta_sqrt_task)(void *vc, long task)
{
    const FN(args_t) *c = (const FN(args_t) *)vc;
    const int64_t e1 = (task + 1) * TET_TASK_EDGES < c->E ? (task + 1) * TET_TASK_EDGES : c->E;
    for (int64_t e = task * TET_TASK_EDGES; e < e1; e++) {
        const T_ *H = c->half + 9 * e, *v = c->vec + 3 * e;
        T_ *t = c->out + 6 * e;
        for (int i = 0; i < 3; i++) {
            t[i] = H[3 * i] * v[0] + H[3 * i + 1] * v[1] + H[3 * i + 2] * v[2];
            t[3 + i] = -(H[i] * v[0] + H[3 + i] * v[1] + H[6 + i] * v[2]);
        }
    }
}

static void FN(theta_sqrt)(const T_ *half, const T_ *vec, T_ *theta, int64_t nb, int64_t E, int threads)
{
    for (int64_t bi = 0; bi < nb; bi++) {
        FN(args_t) c = {.half = half + bi * 9 * E, .vec = vec, .out = theta + bi * 6 * E, .E = E};
        tc_parallel(tc_tasks(E, TET_TASK_EDGES), E >= TET_PAR_MIN ? threads : 1, FN(theta_sqrt_task), &c);
    }
}

int FN(tet_dds_fwd)(const T_ *rot, const T_ *half, const T_ *vec, const int64_t *ridx,
                    const int64_t *tidx, T_ *out, int64_t nb, int64_t E, int64_t T, int threads)
{
    const size_t bytes = sizeof(T_) * 6 * (size_t)(E * nb);
    T_ *theta = tc_scratch(bytes);
    if (!theta)
        return -1;
    FN(theta_sqrt)(half, vec, theta, nb, E, threads);
    FN(tet_dd_fwd)(rot, theta, ridx, tidx, out, nb, E, T, threads);
    tc_scratch_free(theta, bytes);
    return 0;
}

/* ghalf, gvec of the edges of a task (TET_TASK_EDGES) from ∂L/∂θ̃ (gth) */
static void FN(dds_grad_task)(void *vc, long task)
{
    const FN(args_t) *c = (const FN(args_t) *)vc;
    const int64_t e1 = (task + 1) * TET_TASK_EDGES < c->E ? (task + 1) * TET_TASK_EDGES : c->E;
    for (int64_t e = task * TET_TASK_EDGES; e < e1; e++) {
        const T_ *H = c->half + 9 * e, *v = c->vec + 3 * e, *gp = c->gth + 6 * e, *gm = gp + 3;
        /* θ̃_ij = H v: dH += gp v^T, dv += H^T gp; θ̃_ji = -H^T v: dH -= v gm^T, dv -= H gm */
        T_ *gH = c->ghalf + 9 * e;
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                gH[3 * i + j] = gp[i] * v[j] - v[i] * gm[j];
        for (int i = 0; i < 3; i++)
            c->gvec[3 * e + i] = (H[i] * gp[0] + H[3 + i] * gp[1] + H[6 + i] * gp[2])
                               - (H[3 * i] * gm[0] + H[3 * i + 1] * gm[1] + H[3 * i + 2] * gm[2]);
    }
}

int FN(tet_dds_bwd)(const T_ *rot, const T_ *half, const T_ *vec, const T_ *gin,
                    const int64_t *ridx, const int64_t *tidx, const int64_t *order,
                    const int64_t *chunk_start, const int64_t *color_start, int64_t n_colors,
                    T_ *grot, T_ *ghalf, T_ *gvec, int64_t nb, int64_t E, int64_t T, int threads)
{
    const size_t bytes = sizeof(T_) * 6 * (size_t)(E * nb);
    T_ *gth = tc_scratch(bytes); /* ∂L/∂θ̃ (nb, E, 2, 3), zeroed */
    if (!gth)
        return -1;
    /* pass 0 (edges): θ̃ into ghalf's first 6E entries of each item (ghalf has 9E per item and
     * is written only by pass 2); pass 1 (tets, colored chunks): grot and the gradient of every
     * directed θ̃, gth (nb, E, 2, 3), scattered as 3-vectors; pass 2 (edges): ghalf, gvec from
     * gth, once per edge instead of once per (tet, edge) incidence */
    for (int64_t bi = 0; bi < nb; bi++)
        FN(theta_sqrt)(half + bi * 9 * E, vec, ghalf + bi * 9 * E, 1, E, threads);
    FN(zero)(grot, 9 * E * nb, threads);
    for (int64_t c = 0; c < n_colors; c++)
        FN(bwd_item_chunks)(rot, ghalf, gin, ridx, tidx, order, chunk_start, color_start[c],
                            color_start[c + 1] - color_start[c], nb, E, T, 9 * E, grot, gth,
                            threads);
    for (int64_t bi = 0; bi < nb; bi++) {
        FN(args_t) c = {.half = half + bi * 9 * E, .vec = vec, .gth = gth + bi * 6 * E,
                        .ghalf = ghalf + bi * 9 * E, .gvec = gvec + bi * 3 * E, .E = E};
        tc_parallel(tc_tasks(E, TET_TASK_EDGES), E >= TET_PAR_MIN ? threads : 1, FN(dds_grad_task), &c);
    }
    tc_scratch_free(gth, bytes);
    return 0;
}

/* ---- √R formed in the kernel too: θ̃_ij = √R_e v_e, θ̃_ji = -√R_e^T v_e with √R the SO(3)
 * square root of so3.c (torchconn.ops.so3.sqrt), per edge; backward: ∂L/∂R_e = the tet term +
 * the square root's backward of ∂L/∂√R_e, and ∂L/∂v (nb, E, 3) per item. No √R tensor is
 * stored or returned: the roots are recomputed in the backward (blocks of SO3_B edges) */

#define SO3FN(name) TET_CAT(name, TET_SUF)

/* θ̃ of every edge from R (nb, E, 9): roots by blocks of SO3_B edges; task: TET_TASK_SO3 blocks */
static void FN(theta_rot_task)(void *vc, long task)
{
    const FN(args_t) *c = (const FN(args_t) *)vc;
    const int64_t E = c->E, nblk = (E + SO3_B - 1) / SO3_B;
    const int64_t w1 = (task + 1) * TET_TASK_SO3 < nblk ? (task + 1) * TET_TASK_SO3 : nblk;
    for (int64_t w = task * TET_TASK_SO3; w < w1; w++) {
        SO3FN(blk_t) A[9], O[9];
        const int64_t e0 = w * SO3_B;
        const int m = (int)(E - e0 < SO3_B ? E - e0 : SO3_B);
        for (int j = 0; j < m; j++)
            for (int q = 0; q < 9; q++)
                A[q][j] = c->rot[9 * (e0 + j) + q];
        SO3FN(sqrt_fwd_block)(A, O, m, c->eps2);
        for (int j = 0; j < m; j++) {
            const T_ *v = c->vec + 3 * (e0 + j);
            T_ *t = c->out + 6 * (e0 + j);
            for (int i = 0; i < 3; i++) {
                t[i] = O[3 * i][j] * v[0] + O[3 * i + 1][j] * v[1] + O[3 * i + 2][j] * v[2];
                t[3 + i] = -(O[i][j] * v[0] + O[3 + i][j] * v[1] + O[6 + i][j] * v[2]);
            }
        }
    }
}

static void FN(theta_rot)(const T_ *rot, const T_ *vec, T_ *theta, int64_t nb, int64_t E, int threads,
                          T_ eps2)
{
    const int64_t nblk = (E + SO3_B - 1) / SO3_B;
    for (int64_t bi = 0; bi < nb; bi++) {
        FN(args_t) c = {.rot = rot + bi * 9 * E, .vec = vec, .out = theta + bi * 6 * E, .E = E, .eps2 = eps2};
        tc_parallel(tc_tasks(nblk, TET_TASK_SO3), E >= TET_PAR_MIN ? threads : 1, FN(theta_rot_task), &c);
    }
}

int FN(tet_ddr_fwd)(const T_ *rot, const T_ *vec, const int64_t *ridx, const int64_t *tidx, T_ *out,
                    int64_t nb, int64_t E, int64_t T, int threads, double eps)
{
    const size_t bytes = sizeof(T_) * 6 * (size_t)(E * nb);
    T_ *theta = tc_scratch(bytes);
    if (!theta)
        return -1;
    FN(theta_rot)(rot, vec, theta, nb, E, threads, (T_)(eps * eps));
    FN(tet_dd_fwd)(rot, theta, ridx, tidx, out, nb, E, T, threads);
    tc_scratch_free(theta, bytes);
    return 0;
}

/* the edges of a task (TET_TASK_SO3 blocks of SO3_B): √R again, ∂L/∂√R and gvec from gth, and
 * grot += the root's backward */
static void FN(ddr_grad_task)(void *vc, long task)
{
    const FN(args_t) *c = (const FN(args_t) *)vc;
    const int64_t E = c->E, nblk = (E + SO3_B - 1) / SO3_B;
    const int64_t w1 = (task + 1) * TET_TASK_SO3 < nblk ? (task + 1) * TET_TASK_SO3 : nblk;
    for (int64_t w = task * TET_TASK_SO3; w < w1; w++) {
        SO3FN(blk_t) A[9], G[9], O[9];
        const int64_t e0 = w * SO3_B;
        const int m = (int)(E - e0 < SO3_B ? E - e0 : SO3_B);
        for (int j = 0; j < m; j++)
            for (int q = 0; q < 9; q++)
                A[q][j] = c->rot[9 * (e0 + j) + q];
        if (c->gvec) /* H = √R, for ∂L/∂v only: the root's backward below recomputes what it needs */
            SO3FN(sqrt_fwd_block)(A, O, m, c->eps2);
        for (int j = 0; j < m; j++) {
            const T_ *v = c->vec + 3 * (e0 + j), *gp = c->gth + 6 * (e0 + j), *gm = gp + 3;
            /* θ̃_ij = H v: dH += gp v^T, dv += H^T gp; θ̃_ji = -H^T v: dH -= v gm^T, dv -= H gm */
            for (int i = 0; i < 3; i++)
                for (int k = 0; k < 3; k++)
                    G[3 * i + k][j] = gp[i] * v[k] - v[i] * gm[k];
            if (c->gvec) /* NULL: ∂L/∂v not wanted (tet_ddf_sqn without frames) */
                for (int i = 0; i < 3; i++)
                    c->gvec[3 * (e0 + j) + i] = (O[i][j] * gp[0] + O[3 + i][j] * gp[1] + O[6 + i][j] * gp[2])
                                              - (O[3 * i][j] * gm[0] + O[3 * i + 1][j] * gm[1] + O[3 * i + 2][j] * gm[2]);
        }
        SO3FN(sqrt_bwd_block)(A, G, O, m, c->eps2); /* ∂L/∂R through √R */
        for (int j = 0; j < m; j++)
            for (int q = 0; q < 9; q++)
                c->grot[9 * (e0 + j) + q] += O[q][j];
    }
}

int FN(tet_ddr_bwd)(const T_ *rot, const T_ *vec, const T_ *gin, const int64_t *ridx,
                    const int64_t *tidx, const int64_t *order, const int64_t *chunk_start,
                    const int64_t *color_start, int64_t n_colors, T_ *grot, T_ *gvec, int64_t nb,
                    int64_t E, int64_t T, int threads, double eps)
{
    /* pass 0 (edges): θ̃ into a scratch; pass 1 (tets, colored chunks): grot and ∂L/∂θ̃ (gth,
     * a second, zeroed scratch); pass 2 (edges, blocks of SO3_B): √R again, ∂L/∂√R and gvec
     * from gth, and grot += the root's backward */
    const T_ eps2 = (T_)(eps * eps);
    const size_t bytes = sizeof(T_) * 12 * (size_t)(E * nb);
    T_ *theta = tc_scratch(bytes);
    if (!theta)
        return -1;
    T_ *gth = theta + 6 * E * nb;
    FN(theta_rot)(rot, vec, theta, nb, E, threads, eps2);
    FN(zero)(grot, 9 * E * nb, threads);
    for (int64_t c = 0; c < n_colors; c++)
        FN(bwd_item_chunks)(rot, theta, gin, ridx, tidx, order, chunk_start, color_start[c],
                            color_start[c + 1] - color_start[c], nb, E, T, 6 * E, grot, gth,
                            threads);
    const int64_t nblk = (E + SO3_B - 1) / SO3_B;
    for (int64_t bi = 0; bi < nb; bi++) {
        FN(args_t) c = {.rot = rot + bi * 9 * E, .vec = vec, .gth = gth + bi * 6 * E,
                        .grot = grot + bi * 9 * E, .gvec = gvec + bi * 3 * E, .E = E, .eps2 = eps2};
        tc_parallel(tc_tasks(nblk, TET_TASK_SO3), E >= TET_PAR_MIN ? threads : 1, FN(ddr_grad_task), &c);
    }
    tc_scratch_free(theta, bytes);
    return 0;
}

/* ---- the solder form in a frame field (tet_ddf_*): with frames F (nb, V, 9) (axes as columns) and
 * A_e = F_i R_e F_j^T the ambient transport of edge e = (i, j), H = √A_e (so3.c's root, every
 * angle: relabeled frames make A_e a quarter or half turn), θ̃'_ij = F_i^T H v_e (dir 0) and
 * θ̃'_ji = -F_j^T H^T v_e (dir 1) (torchconn.dec.dnabla.tet_solder_sqrt with frames); R itself
 * enters the tet formula. Backward: ∂L/∂R, ∂L/∂F (nb, V, 9) and ∂L/∂v (nb, E, 3) per item; the
 * frame gradients of an edge stripe go to a buffer of their own (stripe 0: the output), summed in
 * stripe order (no atomics; a fixed order for a fixed thread count) */

/* A = F_i R F_j^T of edge e into lane j of the component-major block */
static inline void FN(ambient)(SO3FN(blk_t) *A, int j, const T_ *R, const T_ *Fi, const T_ *Fj)
{
    T_ FR[9];
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++)
            FR[3 * r + c] = Fi[3 * r] * R[c] + Fi[3 * r + 1] * R[3 + c] + Fi[3 * r + 2] * R[6 + c];
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++)
            A[3 * r + c][j] = FR[3 * r] * Fj[3 * c] + FR[3 * r + 1] * Fj[3 * c + 1] + FR[3 * r + 2] * Fj[3 * c + 2];
}

typedef struct {
    const T_ *rot, *fr, *vec, *gth;
    const int64_t *edges;
    T_ *out, *grot, *gvec;
    T_ *gfr[64];
    int64_t E, V, nblk;
    int nt;
    T_ eps2;
} FN(fr_t);

/* θ̃' (E, 2, 3) of every edge; task: TET_TASK_SO3 blocks of SO3_B edges */
static void FN(theta_frames_task)(void *vc, long task)
{
    const FN(fr_t) *c = (const FN(fr_t) *)vc;
    const int64_t E = c->E;
    const int64_t w1 = (task + 1) * TET_TASK_SO3 < c->nblk ? (task + 1) * TET_TASK_SO3 : c->nblk;
    for (int64_t w = task * TET_TASK_SO3; w < w1; w++) {
        SO3FN(blk_t) A[9], O[9];
        const int64_t e0 = w * SO3_B;
        const int m = (int)(E - e0 < SO3_B ? E - e0 : SO3_B);
        for (int j = 0; j < m; j++) {
            const int64_t e = e0 + j;
            FN(ambient)(A, j, c->rot + 9 * e, c->fr + 9 * c->edges[2 * e], c->fr + 9 * c->edges[2 * e + 1]);
        }
        SO3FN(sqrt_fwd_block)(A, O, m, c->eps2);
        for (int j = 0; j < m; j++) {
            const int64_t e = e0 + j;
            const T_ *v = c->vec + 3 * e, *Fi = c->fr + 9 * c->edges[2 * e], *Fj = c->fr + 9 * c->edges[2 * e + 1];
            T_ u[3], w_[3];
            T_ *t = c->out + 6 * e;
            for (int i = 0; i < 3; i++) {
                u[i] = O[3 * i][j] * v[0] + O[3 * i + 1][j] * v[1] + O[3 * i + 2][j] * v[2];  /* H v */
                w_[i] = O[i][j] * v[0] + O[3 + i][j] * v[1] + O[6 + i][j] * v[2];             /* H^T v */
            }
            for (int i = 0; i < 3; i++) {
                t[i] = Fi[i] * u[0] + Fi[3 + i] * u[1] + Fi[6 + i] * u[2];
                t[3 + i] = -(Fj[i] * w_[0] + Fj[3 + i] * w_[1] + Fj[6 + i] * w_[2]);
            }
        }
    }
}

static void FN(theta_frames)(FN(fr_t) *c, int threads)
{
    tc_parallel(tc_tasks(c->nblk, TET_TASK_SO3), c->E >= TET_PAR_MIN ? threads : 1, FN(theta_frames_task), c);
}

int FN(tet_ddf_fwd)(const T_ *rot, const T_ *frames, const T_ *vec, const int64_t *edges, const int64_t *ridx,
                    const int64_t *tidx, T_ *out, int64_t nb, int64_t E, int64_t V, int64_t T, int threads,
                    double eps)
{
    const size_t bytes = sizeof(T_) * 6 * (size_t)(E * nb);
    T_ *theta = tc_scratch(bytes);
    if (!theta)
        return -1;
    for (int64_t bi = 0; bi < nb; bi++) {
        FN(fr_t) c = {.rot = rot + bi * 9 * E, .fr = frames + bi * 9 * V, .vec = vec, .edges = edges,
                      .out = theta + bi * 6 * E, .E = E, .V = V, .nblk = (E + SO3_B - 1) / SO3_B,
                      .eps2 = (T_)(eps * eps)};
        FN(theta_frames)(&c, threads);
    }
    FN(tet_dd_fwd)(rot, theta, ridx, tidx, out, nb, E, T, threads);
    tc_scratch_free(theta, bytes);
    return 0;
}

/* stripe `task` of the edges (whole SO3_B blocks): √A again, the gradients of θ̃' into ∂L/∂H,
 * ∂L/∂v and the frames, the root's backward, ∂L/∂R += F_i^T gA F_j; frame gradients into the
 * stripe's buffer */
static void FN(ddf_grad_task)(void *vc, long task)
{
    const FN(fr_t) *c = (const FN(fr_t) *)vc;
    const int64_t E = c->E;
    T_ *gF = c->gfr[task];
    const int64_t b0 = c->nblk * task / c->nt, b1 = c->nblk * (task + 1) / c->nt;
    if (task > 0)
        memset(gF, 0, sizeof(T_) * 9 * (size_t)c->V);
    for (int64_t w = b0; w < b1; w++) {
        SO3FN(blk_t) A[9], G[9], O[9];
        const int64_t e0 = w * SO3_B;
        const int m = (int)(E - e0 < SO3_B ? E - e0 : SO3_B);
        for (int j = 0; j < m; j++) {
            const int64_t e = e0 + j;
            FN(ambient)(A, j, c->rot + 9 * e, c->fr + 9 * c->edges[2 * e], c->fr + 9 * c->edges[2 * e + 1]);
        }
        SO3FN(sqrt_fwd_block)(A, O, m, c->eps2); /* H = √A */
        for (int j = 0; j < m; j++) {
            const int64_t e = e0 + j, i_ = c->edges[2 * e], j_ = c->edges[2 * e + 1];
            const T_ *v = c->vec + 3 * e, *gp = c->gth + 6 * e, *gm = gp + 3;
            const T_ *Fi = c->fr + 9 * i_, *Fj = c->fr + 9 * j_;
            T_ *gFi = gF + 9 * i_, *gFj = gF + 9 * j_;
            T_ u[3], w_[3], gu[3], gw[3];
            for (int i = 0; i < 3; i++) {
                u[i] = O[3 * i][j] * v[0] + O[3 * i + 1][j] * v[1] + O[3 * i + 2][j] * v[2];
                w_[i] = O[i][j] * v[0] + O[3 + i][j] * v[1] + O[6 + i][j] * v[2];
            }
            /* θ̃'_ij = F_i^T u: dF_i += u gp^T, du = F_i gp; θ̃'_ji = -F_j^T w: dF_j -= w gm^T, dw = -F_j gm */
            for (int i = 0; i < 3; i++) {
                gu[i] = Fi[3 * i] * gp[0] + Fi[3 * i + 1] * gp[1] + Fi[3 * i + 2] * gp[2];
                gw[i] = -(Fj[3 * i] * gm[0] + Fj[3 * i + 1] * gm[1] + Fj[3 * i + 2] * gm[2]);
                for (int k = 0; k < 3; k++) {
                    gFi[3 * i + k] += u[i] * gp[k];
                    gFj[3 * i + k] -= w_[i] * gm[k];
                }
            }
            /* u = H v: dH += gu v^T, dv += H^T gu; w = H^T v: dH += v gw^T, dv += H gw */
            for (int i = 0; i < 3; i++)
                for (int k = 0; k < 3; k++)
                    G[3 * i + k][j] = gu[i] * v[k] + v[i] * gw[k];
            if (c->gvec) /* NULL: ∂L/∂v not wanted (tet_ddf_sqn) */
                for (int i = 0; i < 3; i++)
                    c->gvec[3 * e + i] = (O[i][j] * gu[0] + O[3 + i][j] * gu[1] + O[6 + i][j] * gu[2])
                                       + (O[3 * i][j] * gw[0] + O[3 * i + 1][j] * gw[1] + O[3 * i + 2][j] * gw[2]);
        }
        SO3FN(sqrt_bwd_block)(A, G, O, m, c->eps2); /* O = ∂L/∂A */
        for (int j = 0; j < m; j++) {
            const int64_t e = e0 + j, i_ = c->edges[2 * e], j_ = c->edges[2 * e + 1];
            const T_ *R = c->rot + 9 * e, *Fi = c->fr + 9 * i_, *Fj = c->fr + 9 * j_;
            T_ *gFi = gF + 9 * i_, *gFj = gF + 9 * j_, *gR = c->grot + 9 * e;
            T_ gA[9], P[9], FR[9], RFj[9];
            for (int q = 0; q < 9; q++) gA[q] = O[q][j];
            /* A = F_i R F_j^T: dR += F_i^T gA F_j, dF_i += gA (R F_j^T)^T = gA F_j R^T, dF_j += gA^T F_i R */
            for (int r = 0; r < 3; r++)
                for (int k = 0; k < 3; k++) {
                    P[3 * r + k] = gA[3 * r] * Fj[k] + gA[3 * r + 1] * Fj[3 + k] + gA[3 * r + 2] * Fj[6 + k];    /* gA F_j */
                    FR[3 * r + k] = Fi[3 * r] * R[k] + Fi[3 * r + 1] * R[3 + k] + Fi[3 * r + 2] * R[6 + k];  /* F_i R */
                }
            for (int r = 0; r < 3; r++)
                for (int k = 0; k < 3; k++) {
                    gR[3 * r + k] += Fi[r] * P[k] + Fi[3 + r] * P[3 + k] + Fi[6 + r] * P[6 + k];
                    RFj[3 * r + k] = P[3 * r] * R[3 * k] + P[3 * r + 1] * R[3 * k + 1] + P[3 * r + 2] * R[3 * k + 2];
                }
            for (int q = 0; q < 9; q++) gFi[q] += RFj[q];
            for (int r = 0; r < 3; r++)
                for (int k = 0; k < 3; k++)
                    gFj[3 * r + k] += gA[r] * FR[k] + gA[3 + r] * FR[3 + k] + gA[6 + r] * FR[6 + k];
        }
    }
}

/* out[k] += the other stripes' buffers, in stripe order; task: TET_ZERO_STEP entries */
typedef struct {
    T_ *out;
    T_ *const *bufs;
    int nt;
    int64_t n;
} FN(sumf_t);

static void FN(sumf_task)(void *vc, long task)
{
    const FN(sumf_t) *c = (const FN(sumf_t) *)vc;
    const int64_t k1 = (task + 1) * TET_ZERO_STEP < c->n ? (task + 1) * TET_ZERO_STEP : c->n;
    for (int64_t k = task * TET_ZERO_STEP; k < k1; k++) {
        T_ s = c->out[k];
        for (int t = 1; t < c->nt; t++) s += c->bufs[t][k];
        c->out[k] = s;
    }
}

int FN(tet_ddf_bwd)(const T_ *rot, const T_ *frames, const T_ *vec, const int64_t *edges, const T_ *gin,
                    const int64_t *ridx, const int64_t *tidx, const int64_t *order, const int64_t *chunk_start,
                    const int64_t *color_start, int64_t n_colors, T_ *grot, T_ *gframes, T_ *gvec, int64_t nb,
                    int64_t E, int64_t V, int64_t T, int threads, double eps)
{
    /* pass 0 (edges): θ̃' into a scratch; pass 1 (tets, colored chunks): grot and ∂L/∂θ̃' (gth, a
     * second, zeroed scratch); pass 2 (edge stripes): the chain to H, A, R, F and v; frame
     * buffers of the stripes > 0 in a third scratch, summed into gframes */
    int nt = threads < 1 ? 1 : (threads > 64 ? 64 : threads);
    if (E < TET_PAR_MIN)
        nt = 1;
    const size_t bytes = sizeof(T_) * ((size_t)12 * (size_t)(E * nb) + (size_t)9 * (size_t)V * (size_t)(nt - 1));
    T_ *theta = tc_scratch(bytes);
    if (!theta)
        return -1;
    T_ *gth = theta + 6 * E * nb, *fbuf = gth + 6 * E * nb;
    const T_ eps2 = (T_)(eps * eps);
    const int64_t nblk = (E + SO3_B - 1) / SO3_B;
    for (int64_t bi = 0; bi < nb; bi++) {
        FN(fr_t) c = {.rot = rot + bi * 9 * E, .fr = frames + bi * 9 * V, .vec = vec, .edges = edges,
                      .out = theta + bi * 6 * E, .E = E, .V = V, .nblk = nblk, .eps2 = eps2};
        FN(theta_frames)(&c, threads);
    }
    FN(zero)(grot, 9 * E * nb, threads);
    for (int64_t c = 0; c < n_colors; c++)
        FN(bwd_item_chunks)(rot, theta, gin, ridx, tidx, order, chunk_start, color_start[c],
                            color_start[c + 1] - color_start[c], nb, E, T, 6 * E, grot, gth, threads);
    for (int64_t bi = 0; bi < nb; bi++) {
        FN(fr_t) c = {.rot = rot + bi * 9 * E, .fr = frames + bi * 9 * V, .vec = vec, .edges = edges,
                      .gth = gth + bi * 6 * E, .grot = grot + bi * 9 * E, .gvec = gvec + bi * 3 * E,
                      .E = E, .V = V, .nblk = nblk, .nt = nt, .eps2 = eps2};
        c.gfr[0] = gframes + bi * 9 * V;
        memset(c.gfr[0], 0, sizeof(T_) * 9 * (size_t)V);
        for (int t = 1; t < nt; t++)
            c.gfr[t] = fbuf + (size_t)(t - 1) * 9 * (size_t)V;
        tc_parallel(nt, nt, FN(ddf_grad_task), &c);
        if (nt > 1) {
            FN(sumf_t) s = {c.gfr[0], c.gfr, nt, 9 * V};
            tc_parallel(tc_tasks(9 * V, TET_ZERO_STEP), nt, FN(sumf_task), &s);
        }
    }
    tc_scratch_free(theta, bytes);
    return 0;
}

/* ---- the weighted squared norm of tet_ddf (tet_ddf_sqn_*): per item the value
 * s = sum_t w_t |dd_t|^2 (w (nb, T), dd_t the tet_ddf output) and, with grad, its gradient in the same
 * sweep: the tet pass forms dd_t, adds w_t |dd_t|^2 to its chunk's sum and back-propagates
 * 2 w_t dd_t at once (no (T, 3) output, no separate forward tet pass, θ̃' formed once); frames
 * NULL: the global frame (θ̃ = √R v, as tet_ddr_*; no frame products, no frame gradient); tets with
 * w_t = 0 are neither gathered nor computed. Sums per chunk (grad) or per task (no grad), in
 * double, added in chunk / task order: the value does not depend on the threads. */
typedef struct {
    const T_ *rot, *th, *w;
    const int64_t *ridx, *tidx, *order, *chunk_start;
    T_ *grot, *gth;
    double *part;
    int64_t T, c0;
} FN(sqn_t);

/* the next lanes: up to LANES tets k = order[*s ..] (order NULL: k = *s ..) with w[k] != 0 */
static inline int FN(sqn_lanes)(const T_ *w, const int64_t *order, int64_t *s, int64_t end, int64_t *ks)
{
    int n = 0;
    while (*s < end && n < LANES) {
        const int64_t k = order ? order[*s] : *s;
        ++*s;
        if (w[k] != 0)
            ks[n++] = k;
    }
    return n;
}

/* b->g <- dd of the block (block_fwd); returns sum_l w_l |dd_l|^2 over the n lanes and, with grad,
 * sets b->g <- 2 w_l dd_l (0 on unused lanes) */
static inline double FN(sqn_block)(FN(block) *b, const T_ *w, const int64_t *ks, int n, int grad)
{
    FN(block_fwd)(b);
    double s = 0;
    for (int l = 0; l < LANES; l++) {
        const T_ wl = l < n ? w[ks[l]] : 0;
        if (l < n)
            s += (double)wl * ((double)b->g[0][l] * b->g[0][l] + (double)b->g[1][l] * b->g[1][l]
                               + (double)b->g[2][l] * b->g[2][l]);
        if (grad)
            for (int i = 0; i < 3; i++)
                b->g[i][l] = l < n ? 2 * wl * b->g[i][l] : 0;
    }
    return s;
}

static void FN(sqn_rows)(const FN(sqn_t) *c, const int64_t *ks, int n, const int64_t **ris, const int64_t **tis)
{
    for (int l = 0; l < LANES; l++) {
        const int64_t k = ks[l < n ? l : 0];
        ris[l] = c->ridx + 6 * k;
        tis[l] = c->tidx + 7 * k;
    }
}

/* task: chunk c0 + task of one color (as bwd_chunk_task): value and gradient */
static void FN(sqn_chunk_task)(void *vc, long task)
{
    const FN(sqn_t) *c = (const FN(sqn_t) *)vc;
    const int64_t ch = c->c0 + task, end = c->chunk_start[ch + 1];
    FN(block) b;
    FN(gblock) o;
    int64_t ks[LANES], s0 = c->chunk_start[ch];
    const int64_t *ris[LANES], *tis[LANES];
    double s = 0;
    int n;
    while ((n = FN(sqn_lanes)(c->w, c->order, &s0, end, ks)) > 0) {
        FN(sqn_rows)(c, ks, n, ris, tis);
        FN(gather_block)(&b, n, c->rot, c->th, ris, tis);
        FN(prefetch)(c->rot, c->th, c->grot, c->gth, c->ridx, c->tidx, c->order, s0, end);
        s += FN(sqn_block)(&b, c->w, ks, n, 1);
        FN(block_bwd)(&b, &o);
        for (int l = 0; l < n; l++)
            FN(scatter)(&o, l, c->ridx + 6 * ks[l], c->tidx + 7 * ks[l], c->grot, c->gth);
    }
    c->part[ch] = s;
}

/* task: TET_TASK_BLOCKS * LANES consecutive tets: the value only */
static void FN(sqn_fwd_task)(void *vc, long task)
{
    const FN(sqn_t) *c = (const FN(sqn_t) *)vc;
    const int64_t step = TET_TASK_BLOCKS * LANES;
    const int64_t end = (task + 1) * step < c->T ? (task + 1) * step : c->T;
    FN(block) b;
    int64_t ks[LANES], s0 = task * step;
    const int64_t *ris[LANES], *tis[LANES];
    double s = 0;
    int n;
    while ((n = FN(sqn_lanes)(c->w, NULL, &s0, end, ks)) > 0) {
        FN(sqn_rows)(c, ks, n, ris, tis);
        FN(gather_block)(&b, n, c->rot, c->th, ris, tis);
        s += FN(sqn_block)(&b, c->w, ks, n, 0);
    }
    c->part[task] = s;
}

int FN(tet_ddf_sqn)(const T_ *rot, const T_ *frames, const T_ *vec, const int64_t *edges, const T_ *w,
                    const int64_t *ridx, const int64_t *tidx, const int64_t *order, const int64_t *chunk_start,
                    const int64_t *color_start, int64_t n_colors, double *value, T_ *grot, T_ *gframes,
                    int64_t nb, int64_t E, int64_t V, int64_t T, int threads, double eps, int grad)
{
    /* pass 0 (edges): θ̃' into a scratch; pass 1 (tets): the value and, with grad, grot and ∂L/∂θ̃'
     * (colored chunks, as tet_ddf_bwd); pass 2 (edge stripes, with grad): the chain to R and F */
    int nt = threads < 1 ? 1 : (threads > 64 ? 64 : threads);
    if (E < TET_PAR_MIN)
        nt = 1;
    const int64_t n_chunks = color_start[n_colors], n_tasks = tc_tasks(T, TET_TASK_BLOCKS * LANES);
    const int64_t n_part = grad ? n_chunks : n_tasks;
    const size_t n_fbuf = grad && frames ? (size_t)9 * (size_t)V * (size_t)(nt - 1) : 0;
    const size_t bytes = sizeof(T_) * ((size_t)(grad ? 12 : 6) * (size_t)E + n_fbuf)
                       + sizeof(double) * (size_t)(n_part > 0 ? n_part : 1);
    T_ *theta = tc_scratch(bytes);
    if (!theta)
        return -1;
    T_ *gth = theta + 6 * E, *fbuf = gth + 6 * E;
    double *part = (double *)(theta + (grad ? 12 : 6) * E + n_fbuf);
    const T_ eps2 = (T_)(eps * eps);
    const int64_t nblk = (E + SO3_B - 1) / SO3_B;
    for (int64_t bi = 0; bi < nb; bi++) {
        const T_ *rb = rot + bi * 9 * E, *fb = frames ? frames + bi * 9 * V : NULL;
        FN(fr_t) f = {.rot = rb, .fr = fb, .vec = vec, .edges = edges, .out = theta, .E = E, .V = V,
                      .nblk = nblk, .eps2 = eps2};
        if (fb)
            FN(theta_frames)(&f, threads);
        else
            FN(theta_rot)(rb, vec, theta, 1, E, threads, eps2);
        FN(sqn_t) c = {.rot = rb, .th = theta, .w = w + bi * T, .ridx = ridx, .tidx = tidx, .order = order,
                       .chunk_start = chunk_start, .part = part, .T = T};
        double s = 0;
        if (!grad) {
            tc_parallel(n_tasks, T >= TET_PAR_MIN_TETS ? threads : 1, FN(sqn_fwd_task), &c);
            for (int64_t k = 0; k < n_tasks; k++)
                s += part[k];
            value[bi] = s;
            continue;
        }
        c.grot = grot + bi * 9 * E;
        c.gth = gth;
        FN(zero)(c.grot, 9 * E, threads);
        if (bi > 0)
            FN(zero)(gth, 6 * E, threads);
        for (int64_t k = 0; k < n_colors; k++) {
            const int64_t nc = color_start[k + 1] - color_start[k];
            const int64_t tets = nc > 0 ? chunk_start[color_start[k + 1]] - chunk_start[color_start[k]] : 0;
            c.c0 = color_start[k];
            tc_parallel(nc, tets >= TET_PAR_MIN_TETS ? threads : 1, FN(sqn_chunk_task), &c);
        }
        for (int64_t k = 0; k < n_chunks; k++)
            s += part[k];
        value[bi] = s;
        if (!fb) { /* the chain to R through √R only (as tet_ddr_bwd's pass 2, without ∂L/∂v) */
            FN(args_t) a = {.rot = rb, .vec = vec, .gth = gth, .grot = c.grot, .gvec = NULL, .E = E, .eps2 = eps2};
            tc_parallel(tc_tasks(nblk, TET_TASK_SO3), E >= TET_PAR_MIN ? threads : 1, FN(ddr_grad_task), &a);
            continue;
        }
        f.gth = gth;
        f.grot = c.grot;
        f.gvec = NULL;
        f.nt = nt;
        f.gfr[0] = gframes + bi * 9 * V;
        memset(f.gfr[0], 0, sizeof(T_) * 9 * (size_t)V);
        for (int t = 1; t < nt; t++)
            f.gfr[t] = fbuf + (size_t)(t - 1) * 9 * (size_t)V;
        tc_parallel(nt, nt, FN(ddf_grad_task), &f);
        if (nt > 1) {
            FN(sumf_t) su = {f.gfr[0], f.gfr, nt, 9 * V};
            tc_parallel(tc_tasks(9 * V, TET_ZERO_STEP), nt, FN(sumf_task), &su);
        }
    }
    tc_scratch_free(theta, bytes);
    return 0;
}

#undef SO3FN

#undef RL
#undef MV_L
#undef MTV_L
#undef FORWARD_LANE
#undef S6
#undef S3
#undef HALF
#undef T_
#undef FN

#endif /* TET_T */


