/* Face curvature of sorted-triangle meshes, forward and backward (issue 11; loaded by
 * torchconn/ops/native.py, dispatched by torchconn/ops/curvature.py).
 *
 * For every sorted face [a<b<c] with the canonical edge rotations R_ab, R_bc, R_ac (row-major
 * 3x3, gathered from edge_rot by the index table face_index (3, F): rows ab, bc, ac), kind:
 *   2 (cut c)    H = R_ab R_bc - R_ac
 *   1 (cut b)    H = R_ab - R_ac R_bc^T
 *   0 (holonomy) H = R_ab R_bc R_ac^T - I
 * the same products, in the same order of operations, as the generic torch kernel
 * (ops/curvature.py, _face_formula: each entry a0*b0 + a1*b1 + a2*b2 left to right; compiled with
 * -std=c99, i.e. no FMA contraction), so both agree to round-off.
 *
 * Backward, with G = dL/dH of the face:
 *   kind 2: g_ab = G R_bc^T, g_bc = R_ab^T G, g_ac = -G
 *   kind 1: g_ab = G, g_bc = -G^T R_ac, g_ac = -G R_bc
 *   kind 0: g_ab = (G R_ac) R_bc^T, g_bc = R_ab^T (G R_ac), g_ac = G^T (R_ab R_bc)
 * summed over the faces incident to each edge. The sum is race-free without atomics: the loop
 * runs over *edges* (tasks of the pool, pool.c), each reading its incident (face, slot) pairs from a CSR table
 * built once per mesh (inc_ptr (E + 1), inc (3F) = 3 f + slot, slot 0 = ab, 1 = bc, 2 = ac, in
 * increasing order), and computes only the slot's term. Every face term is thus computed once
 * (3F slot terms in all, as a face loop would), each edge is written once, and the sum over a
 * given edge is in a fixed order: results do not depend on the number of threads.
 *
 * The weighted squared norm (curv_sqn_*, issue 30): per batch item s = sum_f w_f |H_f|_F^2 and,
 * with a gradient buffer, ds/dR: a face pass forms H_f once, adds w_f |H_f|^2 to its task's sum and
 * writes G_f = 2 w_f H_f to a scratch (freed before return; no (F, 3, 3) tensor, square or
 * backward tensor of torch), and the backward edge pass above turns G into ds/dR. Faces with
 * w_f = 0 are not computed. Sums per task in double, added in task order (the value does not
 * depend on the number of threads).
 *
 * Leading batch dims: edge_rot (B, E, 9), grad/out (B, F, 9), w (B, F); the batch is looped inside.
 * Exported: curv_fwd_{f32,f64}(const T* edge_rot, const long* face_index, T* out, long B,
 *                              long E, long F, int kind, int nthreads)
 *           curv_bwd_{f32,f64}(const T* edge_rot, const T* grad, const long* face_index,
 *                              const int* inc_ptr, const int* inc, T* grad_edge, long B,
 *                              long E, long F, int kind, int nthreads)
 *           int curv_sqn_{f32,f64}(const T* edge_rot, const T* w, const long* face_index,
 *                              const int* inc_ptr, const int* inc, double* value,
 *                              T* grad_edge (NULL: the value only), long B, long E, long F,
 *                              int kind, int nthreads) -> 0, or -1 when its task sums cannot be
 *                              allocated
 */
#ifndef CURV_T

#define _DEFAULT_SOURCE /* mmap's MAP_ANONYMOUS (tc_scratch of pool.c) */
#include <stddef.h> /* NULL */

#define CURV_CAT_(a, b) a##b
#define CURV_CAT(a, b) CURV_CAT_(a, b)
/* loops smaller than this run on the calling thread (no pool wake-up): torch's own grain
 * size (at::internal::GRAIN_SIZE), so that small meshes are not slower than the generic
 * kernel, whose loops run single-threaded below it (measured with OpenMP on a loaded 2-core
 * machine: 2048 made box(8) ~4x slower than the torch kernel there) */
#define CURV_PAR_MIN 32768L
/* faces / edges per task of the pool */
#define CURV_TASK 2048L

#define TC_POOL_CLIENT
#define TC_POOL_SCRATCH /* tc_scratch */
#include "pool.c" /* tc_parallel */

#define CURV_T float
#define CURV_SUF _f32
#include "curvature.c" /* this file, again (quoted includes resolve next to it) */
#undef CURV_T
#undef CURV_SUF

#define CURV_T double
#define CURV_SUF _f64
#include "curvature.c"

#else /* ------------------------------------------------------------- one dtype */

#define T CURV_T
#define FN(name) CURV_CAT(name, CURV_SUF)

/* C = A B (row-major 3x3) */
static inline void FN(mm)(const T *A, const T *B, T *C)
{
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}

/* C = A B^T */
static inline void FN(mmt)(const T *A, const T *B, T *C)
{
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[3 * i] * B[3 * j] + A[3 * i + 1] * B[3 * j + 1] + A[3 * i + 2] * B[3 * j + 2];
}

/* C = A^T B */
static inline void FN(mtm)(const T *A, const T *B, T *C)
{
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[i] * B[j] + A[3 + i] * B[3 + j] + A[6 + i] * B[6 + j];
}

/* h = H of the face with rotations ab, bc, ac (the formulas of the header, kind 0 with the - I) */
static inline void FN(face_h)(int kind, const T *ab, const T *bc, const T *ac, T *h)
{
    T P[9];
    if (kind == 2) {
        FN(mm)(ab, bc, P);
        for (int q = 0; q < 9; ++q)
            h[q] = P[q] - ac[q];
    } else if (kind == 1) {
        FN(mmt)(ac, bc, P);
        for (int q = 0; q < 9; ++q)
            h[q] = ab[q] - P[q];
    } else {
        FN(mm)(ab, bc, P);
        FN(mmt)(P, ac, h);
        h[0] -= (T)1; h[4] -= (T)1; h[8] -= (T)1;
    }
}

/* the arguments of one item of a curvature loop (a task covers CURV_TASK faces or edges) */
typedef struct {
    const T *R, *G, *w;
    const long *face_index;
    const int *inc_ptr, *inc;
    T *out;
    double *part;
    long E, F;
    int kind;
} FN(curv_t);

static void FN(fwd_task)(void *vc, long task)
{
    const FN(curv_t) *c = (const FN(curv_t) *)vc;
    const long F = c->F, f1 = (task + 1) * CURV_TASK < F ? (task + 1) * CURV_TASK : F;
    const long *iab = c->face_index, *ibc = c->face_index + F, *iac = c->face_index + 2 * F;
    const T *R = c->R;
    const int kind = c->kind;
    for (long f = task * CURV_TASK; f < f1; ++f)
        FN(face_h)(kind, R + iab[f] * 9, R + ibc[f] * 9, R + iac[f] * 9, c->out + f * 9);
}

void FN(curv_fwd)(const T *edge_rot, const long *face_index, T *out, long B, long E, long F, int kind,
                  int nt)
{
    for (long b = 0; b < B; ++b) {
        FN(curv_t) c = {.R = edge_rot + b * E * 9, .face_index = face_index, .out = out + b * F * 9,
                        .E = E, .F = F, .kind = kind};
        tc_parallel(tc_tasks(F, CURV_TASK), F >= CURV_PAR_MIN ? nt : 1, FN(fwd_task), &c);
    }
}

/* the term of slot s (0 ab, 1 bc, 2 ac) of face f: g += dH/dR_slot^T G. Only the rotations the
 * term needs are looked up: the face's rows of face_index are three scattered reads (cache
 * misses at 1M tets), and kind 2 needs one of them per slot, not three (one thread: 43 -> 33 ms) */
#define CURV_ROT(slot) (R + face_index[(slot) * F + f] * 9)
static inline void FN(slot_term)(int kind, int s, const T *R, const long *face_index, long F, long f,
                                 const T *G, T *g)
{
    T t[9], u[9];
    if (kind == 2) {
        if (s == 0) FN(mmt)(G, CURV_ROT(1), t);
        else if (s == 1) FN(mtm)(CURV_ROT(0), G, t);
        else for (int q = 0; q < 9; ++q) t[q] = -G[q];
    } else if (kind == 1) {
        if (s == 0) for (int q = 0; q < 9; ++q) t[q] = G[q];
        else if (s == 1) { FN(mtm)(G, CURV_ROT(2), u); for (int q = 0; q < 9; ++q) t[q] = -u[q]; }
        else { FN(mm)(G, CURV_ROT(1), u); for (int q = 0; q < 9; ++q) t[q] = -u[q]; }
    } else {
        if (s == 0) { FN(mm)(G, CURV_ROT(2), u); FN(mmt)(u, CURV_ROT(1), t); }
        else if (s == 1) { FN(mm)(G, CURV_ROT(2), u); FN(mtm)(CURV_ROT(0), u, t); }
        else { FN(mm)(CURV_ROT(0), CURV_ROT(1), u); FN(mtm)(G, u, t); }
    }
    for (int q = 0; q < 9; ++q)
        g[q] += t[q];
}
#undef CURV_ROT

static void FN(bwd_task)(void *vc, long task)
{
    const FN(curv_t) *c = (const FN(curv_t) *)vc;
    const long e1 = (task + 1) * CURV_TASK < c->E ? (task + 1) * CURV_TASK : c->E;
    for (long e = task * CURV_TASK; e < e1; ++e) {
        T g[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
        for (int k = c->inc_ptr[e]; k < c->inc_ptr[e + 1]; ++k) {
            const long f = c->inc[k] / 3;
            const int s = c->inc[k] - 3 * (int)f;
            FN(slot_term)(c->kind, s, c->R, c->face_index, c->F, f, c->G + f * 9, g);
        }
        for (int q = 0; q < 9; ++q)
            c->out[e * 9 + q] = g[q];
    }
}

void FN(curv_bwd)(const T *edge_rot, const T *grad, const long *face_index, const int *inc_ptr,
                  const int *inc, T *grad_edge, long B, long E, long F, int kind, int nt)
{
    for (long b = 0; b < B; ++b) {
        FN(curv_t) c = {.R = edge_rot + b * E * 9, .G = grad + b * F * 9, .face_index = face_index,
                        .inc_ptr = inc_ptr, .inc = inc, .out = grad_edge + b * E * 9, .E = E, .F = F,
                        .kind = kind};
        tc_parallel(tc_tasks(E, CURV_TASK), E >= CURV_PAR_MIN ? nt : 1, FN(bwd_task), &c);
    }
}

/* curv_sqn: the faces of a task: the value and, with a gradient buffer G, G_f = 2 w_f H_f */
static void FN(sqn_task)(void *vc, long task)
{
    const FN(curv_t) *c = (const FN(curv_t) *)vc;
    const long F = c->F, f1 = (task + 1) * CURV_TASK < F ? (task + 1) * CURV_TASK : F;
    const long *fi = c->face_index;
    T *G = c->out;
    double s = 0;
    for (long f = task * CURV_TASK; f < f1; ++f) {
        const T wf = c->w[f];
        T h[9];
        if (wf == 0) {
            if (G)
                for (int q = 0; q < 9; ++q)
                    G[f * 9 + q] = 0;
            continue;
        }
        FN(face_h)(c->kind, c->R + fi[f] * 9, c->R + fi[F + f] * 9, c->R + fi[2 * F + f] * 9, h);
        double n2 = 0;
        for (int q = 0; q < 9; ++q)
            n2 += (double)h[q] * h[q];
        s += (double)wf * n2;
        if (G)
            for (int q = 0; q < 9; ++q)
                G[f * 9 + q] = 2 * wf * h[q];
    }
    c->part[task] = s;
}

int FN(curv_sqn)(const T *edge_rot, const T *w, const long *face_index, const int *inc_ptr, const int *inc,
                 double *value, T *grad_edge, long B, long E, long F, int kind, int nt)
{
    /* pass 1 (faces): the value and, with a gradient, G = 2 w H into a scratch (F, 9); pass 2
     * (edges, bwd_task): the gradient from G, race-free. Recomputing H per incident face in the
     * edge pass instead (no scratch) reads three rotations and three index rows per incidence,
     * scattered: 0.21 s at 1M tets against 0.07 s for the two passes */
    const long tasks = tc_tasks(F, CURV_TASK), n_part = tasks > 0 ? tasks : 1;
    const size_t bytes = sizeof(double) * (size_t)n_part + (grad_edge ? sizeof(T) * 9 * (size_t)F : 0);
    double *part = tc_scratch(bytes);
    if (!part)
        return -1;
    T *G = grad_edge ? (T *)(part + n_part) : NULL;
    for (long b = 0; b < B; ++b) {
        FN(curv_t) c = {.R = edge_rot + b * E * 9, .w = w + b * F, .face_index = face_index,
                        .inc_ptr = inc_ptr, .inc = inc, .out = G, .part = part, .E = E, .F = F,
                        .kind = kind};
        tc_parallel(tasks, F >= CURV_PAR_MIN ? nt : 1, FN(sqn_task), &c);
        double s = 0;
        for (long k = 0; k < tasks; ++k)
            s += part[k];
        value[b] = s;
        if (grad_edge) {
            c.G = G;
            c.out = grad_edge + b * E * 9;
            tc_parallel(tc_tasks(E, CURV_TASK), E >= CURV_PAR_MIN ? nt : 1, FN(bwd_task), &c);
        }
    }
    tc_scratch_free(part, bytes);
    return 0;
}

#undef T
#undef FN

#endif /* CURV_T */
