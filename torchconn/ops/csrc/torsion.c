/* √R face torsion of sorted-triangle meshes, forward and backward (issue 30; loaded by
 * torchconn/ops/native.py, dispatched by torchconn/ops/torsion.py: the CPU kernels of the ops
 * torchconn::face_torsion_sqrt and torchconn::face_torsion_sqrt_backward).
 *
 * For every sorted face [a<b<c] with canonical edges ab, bc, ac (face_index (3, F)):
 *   Θ_f = θ̃_ab + R_ab θ̃_bc - θ̃_ac,   θ̃_e = √R_e v_e  (v_e = v_j - v_i, report Def. 3.2)
 * with √R the SO(3) square root of so3.c (its element kernels, included below: every angle,
 * the same values as torchconn.ops.so3.sqrt). θ̃ is formed once per *edge* (pass A, blocks of
 * SO3_B edges, into a scratch mapped per call, tc_scratch of pool.c), then every face reads three of them
 * (pass B, a face loop writing its own row): no √R tensor, no (F, 3, 3) gather.
 *
 * Backward, with G_f = dL/dΘ_f: the gradient of θ̃_e sums the slots of the faces incident to e
 * (slot ab: G_f; bc: R_ab^T G_f; ac: -G_f) and dL/dR_e the ab slots' G_f θ̃_bc^T; the loop runs
 * over *edges* (pass C, blocks of SO3_B edges), each reading its incident (face, slot) pairs from
 * the CSR table of torchconn.ops.curvature (inc_ptr (E + 1), inc (3F) = 3 f + slot, slot 0 = ab,
 * 1 = bc, 2 = ac): race-free without atomics or per-thread buffers, each edge written once, the
 * sum over an edge in a fixed order (the result does not depend on the number of threads). The
 * block then turns dL/dθ̃ into dL/dv = √R^T gθ and dL/d√R = gθ v^T, and dL/dR += the root's
 * backward (so3.c).
 *
 * Leading batch dims: rot (B, E, 9), out/grad (B, F, 3), grot (B, E, 9), gvec (B, E, 3) per item
 * (summed by the caller); vec (E, 3) shared. Exported (T = float / double, SUF = f32 / f64):
 *   int tor_fwd_SUF(rot, vec, face_index, out, B, E, F, threads, eps)
 *   int tor_bwd_SUF(rot, vec, face_index, inc_ptr, inc, grad, grot, gvec, B, E, F, threads, eps)
 * (eps: the so3 small-angle threshold; 0, or -1 when the scratch cannot be mapped)
 */
#ifndef TOR_T

#define _DEFAULT_SOURCE /* mmap's MAP_ANONYMOUS (tc_scratch of pool.c) */
#include <stdint.h>
#include <string.h>

/* the SO(3) square root and its backward, on blocks of SO3_B matrices (the one home of those
 * formulas) */
#define SO3_KERNELS_ONLY
#include "so3.c"
#undef SO3_KERNELS_ONLY

#define TOR_CAT_(a, b) a##b
#define TOR_CAT(a, b) TOR_CAT_(a, b)
/* loops smaller than this run on the calling thread (no pool wake-up) */
#define TOR_PAR_MIN 32768L
/* faces per task of the face loop; SO3_B-edge blocks per task of the edge loops */
#define TOR_TASK_FACES 4096L
#define TOR_TASK_BLOCKS 16L

#define TC_POOL_CLIENT
#define TC_POOL_SCRATCH /* tc_scratch */
#include "pool.c" /* tc_parallel */

#define TOR_T float
#define TOR_SUF _f32
#include "torsion.c" /* this file, again (quoted includes resolve next to it) */
#undef TOR_T
#undef TOR_SUF

#define TOR_T double
#define TOR_SUF _f64
#include "torsion.c"

#else /* ------------------------------------------------------------- one dtype */

#define T_ TOR_T
#define FN(name) TOR_CAT(name, TOR_SUF)
#define SO3FN(name) TOR_CAT(name, TOR_SUF)

typedef struct {
    const T_ *rot, *vec, *grad;
    const int64_t *fi;
    const int32_t *inc_ptr, *inc;
    T_ *theta, *gth, *out, *grot, *gvec;
    int64_t E, F, nblk;
    T_ eps2;
} FN(tor_t);

/* pass A: θ̃_e = √R_e v_e; task: TOR_TASK_BLOCKS blocks of SO3_B edges */
static void FN(theta_task)(void *vc, long task)
{
    const FN(tor_t) *c = (const FN(tor_t) *)vc;
    const int64_t E = c->E;
    const int64_t w1 = (task + 1) * TOR_TASK_BLOCKS < c->nblk ? (task + 1) * TOR_TASK_BLOCKS : c->nblk;
    for (int64_t w = task * TOR_TASK_BLOCKS; w < w1; w++) {
        SO3FN(blk_t) A[9], O[9];
        const int64_t e0 = w * SO3_B;
        const int m = (int)(E - e0 < SO3_B ? E - e0 : SO3_B);
        for (int j = 0; j < m; j++)
            for (int q = 0; q < 9; q++)
                A[q][j] = c->rot[9 * (e0 + j) + q];
        SO3FN(sqrt_fwd_block)(A, O, m, c->eps2);
        for (int j = 0; j < m; j++) {
            const T_ *v = c->vec + 3 * (e0 + j);
            T_ *t = c->theta + 3 * (e0 + j);
            for (int i = 0; i < 3; i++)
                t[i] = O[3 * i][j] * v[0] + O[3 * i + 1][j] * v[1] + O[3 * i + 2][j] * v[2];
        }
    }
}

static void FN(theta)(FN(tor_t) *c, int threads)
{
    tc_parallel(tc_tasks(c->nblk, TOR_TASK_BLOCKS), c->E >= TOR_PAR_MIN ? threads : 1, FN(theta_task), c);
}

/* pass B: Θ_f = θ̃_ab + R_ab θ̃_bc - θ̃_ac; task: TOR_TASK_FACES faces */
static void FN(face_task)(void *vc, long task)
{
    const FN(tor_t) *c = (const FN(tor_t) *)vc;
    const int64_t F = c->F, f1 = (task + 1) * TOR_TASK_FACES < F ? (task + 1) * TOR_TASK_FACES : F;
    const int64_t *iab = c->fi, *ibc = c->fi + F, *iac = c->fi + 2 * F;
    for (int64_t f = task * TOR_TASK_FACES; f < f1; f++) {
        const T_ *R = c->rot + 9 * iab[f], *ab = c->theta + 3 * iab[f], *bc = c->theta + 3 * ibc[f];
        const T_ *ac = c->theta + 3 * iac[f];
        T_ *o = c->out + 3 * f;
        for (int i = 0; i < 3; i++)
            o[i] = ab[i] - ac[i] + (R[3 * i] * bc[0] + R[3 * i + 1] * bc[1] + R[3 * i + 2] * bc[2]);
    }
}

int FN(tor_fwd)(const T_ *rot, const T_ *vec, const int64_t *fi, T_ *out, int64_t B, int64_t E, int64_t F,
                int threads, double eps)
{
    const size_t bytes = sizeof(T_) * 3 * (size_t)E;
    T_ *theta = tc_scratch(bytes);
    if (!theta)
        return -1;
    for (int64_t b = 0; b < B; b++) {
        FN(tor_t) c = {.rot = rot + b * 9 * E, .vec = vec, .fi = fi, .theta = theta, .out = out + b * 3 * F,
                       .E = E, .F = F, .nblk = (E + SO3_B - 1) / SO3_B, .eps2 = (T_)(eps * eps)};
        FN(theta)(&c, threads);
        tc_parallel(tc_tasks(F, TOR_TASK_FACES), F >= TOR_PAR_MIN ? threads : 1, FN(face_task), &c);
    }
    tc_scratch_free(theta, bytes);
    return 0;
}

/* pass C: the edges of TOR_TASK_BLOCKS blocks: gθ and the ab slots' dL/dR from the incident faces,
 * then dL/dv, dL/d√R and the root's backward */
static void FN(bwd_task)(void *vc, long task)
{
    const FN(tor_t) *c = (const FN(tor_t) *)vc;
    const int64_t E = c->E, F = c->F;
    const int64_t *ibc = c->fi + F, *iab = c->fi;
    const int64_t w1 = (task + 1) * TOR_TASK_BLOCKS < c->nblk ? (task + 1) * TOR_TASK_BLOCKS : c->nblk;
    for (int64_t w = task * TOR_TASK_BLOCKS; w < w1; w++) {
        SO3FN(blk_t) A[9], Gs[9], O[9];
        const int64_t e0 = w * SO3_B;
        const int m = (int)(E - e0 < SO3_B ? E - e0 : SO3_B);
        for (int j = 0; j < m; j++) {
            const int64_t e = e0 + j;
            T_ gt[3] = {0, 0, 0}, gr[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
            for (int32_t k = c->inc_ptr[e]; k < c->inc_ptr[e + 1]; k++) {
                const int64_t f = c->inc[k] / 3;
                const int s = c->inc[k] - 3 * (int)f;
                const T_ *G = c->grad + 3 * f;
                if (s == 0) {  /* ab: θ̃_ab and R_ab (with θ̃_bc) */
                    const T_ *bc = c->theta + 3 * ibc[f];
                    for (int i = 0; i < 3; i++) {
                        gt[i] += G[i];
                        for (int q = 0; q < 3; q++)
                            gr[3 * i + q] += G[i] * bc[q];
                    }
                } else if (s == 1) {  /* bc: R_ab^T G */
                    const T_ *Rab = c->rot + 9 * iab[f];
                    for (int i = 0; i < 3; i++)
                        gt[i] += Rab[i] * G[0] + Rab[3 + i] * G[1] + Rab[6 + i] * G[2];
                } else {  /* ac */
                    for (int i = 0; i < 3; i++)
                        gt[i] -= G[i];
                }
            }
            const T_ *v = c->vec + 3 * e;
            for (int q = 0; q < 9; q++) {
                A[q][j] = c->rot[9 * e + q];
                c->grot[9 * e + q] = gr[q];
            }
            for (int i = 0; i < 3; i++)
                for (int q = 0; q < 3; q++)
                    Gs[3 * i + q][j] = gt[i] * v[q];  /* θ̃ = √R v: dL/d√R = gθ v^T */
            for (int i = 0; i < 3; i++)
                c->gth[3 * e + i] = gt[i];  /* kept for dL/dv below (θ̃ itself is read by other edges) */
        }
        SO3FN(sqrt_fwd_block)(A, O, m, c->eps2);
        for (int j = 0; j < m; j++) {  /* dL/dv = √R^T gθ */
            const int64_t e = e0 + j;
            const T_ *gt = c->gth + 3 * e;
            for (int i = 0; i < 3; i++)
                c->gvec[3 * e + i] = O[i][j] * gt[0] + O[3 + i][j] * gt[1] + O[6 + i][j] * gt[2];
        }
        SO3FN(sqrt_bwd_block)(A, Gs, O, m, c->eps2);
        for (int j = 0; j < m; j++)
            for (int q = 0; q < 9; q++)
                c->grot[9 * (e0 + j) + q] += O[q][j];
    }
}

int FN(tor_bwd)(const T_ *rot, const T_ *vec, const int64_t *fi, const int32_t *inc_ptr, const int32_t *inc,
                const T_ *grad, T_ *grot, T_ *gvec, int64_t B, int64_t E, int64_t F, int threads, double eps)
{
    /* θ̃ (E, 3), read by the ab slots of other edges (their θ̃_bc), and gθ (E, 3) */
    const size_t bytes = sizeof(T_) * 6 * (size_t)E;
    T_ *theta = tc_scratch(bytes);
    if (!theta)
        return -1;
    for (int64_t b = 0; b < B; b++) {
        FN(tor_t) c = {.rot = rot + b * 9 * E, .vec = vec, .fi = fi, .inc_ptr = inc_ptr, .inc = inc,
                       .grad = grad + b * 3 * F, .theta = theta, .gth = theta + 3 * E, .grot = grot + b * 9 * E,
                       .gvec = gvec + b * 3 * E, .E = E, .F = F, .nblk = (E + SO3_B - 1) / SO3_B,
                       .eps2 = (T_)(eps * eps)};
        FN(theta)(&c, threads);
        tc_parallel(tc_tasks(c.nblk, TOR_TASK_BLOCKS), E >= TOR_PAR_MIN ? threads : 1, FN(bwd_task), &c);
    }
    tc_scratch_free(theta, bytes);
    return 0;
}

#undef SO3FN
#undef FN
#undef T_

#endif /* TOR_T */
