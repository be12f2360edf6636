/* Per-tet frames from per-vertex frames, smoothed (the rule of torchconn.hexmesh.energy.smooth_tet_frames),
 * forward and first-order backward (loaded by torchconn/ops/native.py as a registered source,
 * dispatched by torchconn/frames/kernels/tet_frames.py).
 *
 * Tet t with lowest vertex a and its other three vertices o_k, matchings g_tk (3x3, F_a g ~ F_ok):
 *   M = (F_a + sum_k F_ok g_k^T) / 4,  X = F_a^T M,  R = polar(X),  Y_t = F_a R
 * the polar factor by the scaled Newton iteration X <- (z X + (z X)^{-T}) / 2,
 * z = (|X^{-T}|_F / |X|_F)^{1/2} (Higham), per matrix, stopped one step after its largest entry
 * change falls below tol, at most max_iters steps (the torch code stops on the largest change
 * over all tets: the two agree to round-off).
 *
 * Backward for G = dL/dY (the closed form of the polar factor's derivative, as _Polar in
 * torchconn/hexmesh/energy.py): with S = sym(R^T X), P = tr(S) I - S, w = P^{-1} axial(R^T F_a^T G),
 *   dX = R [w]_x,  dM = F_a dX,  H = dM / 4,  dF_a = G R^T + M dX^T + H,  dF_ok = H g_k
 * per tet (a tet pass into two (T, 9) scratch rows), then summed per vertex over its incident
 * (tet, slot) pairs from a CSR table (inc_ptr (V + 1), inc (4T) = 4 t + slot, slot 0 = a, k = o_k):
 * race-free, in a fixed order (the result does not depend on the threads).
 *
 * Exported (T = float | double, SFX _f32 | _f64):
 *   long stf_fwd_SFX(long NT, long V, int nt, const T* F, const int64_t* a, const int64_t* o,
 *                    const T* g, T tol, int max_iters, T* Y, T* M, T* R, int64_t* first_bad)
 *       -> the number of tets whose X has det <= 0 (their outputs are not meaningful; first_bad
 *          receives the lowest such index), 0 when every tet is fine
 *   int stf_bwd_SFX(long NT, long V, int nt, const T* F, const int64_t* a, const int64_t* o,
 *                   const T* g, const T* M, const T* R, const T* G, const int64_t* inc_ptr,
 *                   const int64_t* inc, T* gF) -> 0, or -1 when the scratch cannot be mapped
 */
#ifndef TC_BODY

#define _DEFAULT_SOURCE /* mmap's MAP_ANONYMOUS (tc_scratch of pool.c) */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

#define TC_POOL_CLIENT
#define TC_POOL_SCRATCH /* tc_scratch */
#include "pool.c" /* tc_parallel */

/* tets / vertices per task of the pool; loops below STF_PAR_MIN items run on the calling thread */
#define STF_TASK 2048L
#define STF_PAR_MIN 32768L

#define TC_BODY
#define T float
#define SFX(n) n##_f32
#define SQRT sqrtf
#include __FILE__
#undef T
#undef SFX
#undef SQRT

#define T double
#define SFX(n) n##_f64
#define SQRT sqrt
#include __FILE__
#undef T
#undef SFX
#undef SQRT

#else /* ------------------------------------------------------------------ body, T = float | double */

/* C = A B, C = A^T B, C = A B^T (row-major 3x3) */
static inline void SFX(mm)(const T* A, const T* B, T* C) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}
static inline void SFX(mtm)(const T* A, const T* B, T* C) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) C[3 * i + j] = A[i] * B[j] + A[3 + i] * B[3 + j] + A[6 + i] * B[6 + j];
}
static inline void SFX(mmt)(const T* A, const T* B, T* C) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[3 * i] * B[3 * j] + A[3 * i + 1] * B[3 * j + 1] + A[3 * i + 2] * B[3 * j + 2];
}

/* cof = the cofactor matrix of x (x^{-T} = cof / det); returns det */
static inline T SFX(cofactor)(const T* x, T* cof) {
    cof[0] = x[4] * x[8] - x[5] * x[7];
    cof[1] = x[5] * x[6] - x[3] * x[8];
    cof[2] = x[3] * x[7] - x[4] * x[6];
    cof[3] = x[2] * x[7] - x[1] * x[8];
    cof[4] = x[0] * x[8] - x[2] * x[6];
    cof[5] = x[1] * x[6] - x[0] * x[7];
    cof[6] = x[1] * x[5] - x[2] * x[4];
    cof[7] = x[2] * x[3] - x[0] * x[5];
    cof[8] = x[0] * x[4] - x[1] * x[3];
    return x[0] * cof[0] + x[1] * cof[1] + x[2] * cof[2];
}

typedef struct {
    const T *F, *g, *M, *R, *G;
    const int64_t *a, *o, *inc_ptr, *inc;
    T *Y, *Mo, *Ro, *gF, *dFa, *H;
    T tol;
    int max_iters;
    long NT, V;
    int64_t *bad;  /* per task: the number of bad tets, then the first one */
} SFX(stf_t);

static void SFX(fwd_task)(void* vc, long task) {
    const SFX(stf_t)* c = (const SFX(stf_t)*)vc;
    const long t1 = (task + 1) * STF_TASK < c->NT ? (task + 1) * STF_TASK : c->NT;
    int64_t nbad = 0, first = -1;
    for (long t = task * STF_TASK; t < t1; ++t) {
        const T* Fa = c->F + 9 * c->a[t];
        T M[9], P[9], x[9], cof[9];
        for (int q = 0; q < 9; ++q) M[q] = Fa[q];
        for (int k = 0; k < 3; ++k) {
            SFX(mmt)(c->F + 9 * c->o[3 * t + k], c->g + 27 * t + 9 * k, P); /* F_ok g_k^T */
            for (int q = 0; q < 9; ++q) M[q] += P[q];
        }
        for (int q = 0; q < 9; ++q) M[q] *= (T)0.25;
        SFX(mtm)(Fa, M, x); /* X = F_a^T M */
        for (int q = 0; q < 9; ++q) c->Mo[9 * t + q] = M[q];
        T det = SFX(cofactor)(x, cof);
        if (!(det > 0)) {
            if (nbad++ == 0) first = t;
            for (int q = 0; q < 9; ++q) c->Ro[9 * t + q] = c->Y[9 * t + q] = 0;
            continue;
        }
        int last = 0;
        for (int it = 0; it < c->max_iters; ++it) {
            T ni = 0, nx = 0, change = 0, xn[9];
            for (int q = 0; q < 9; ++q) {
                cof[q] /= det; /* x^{-T} */
                ni += cof[q] * cof[q];
                nx += x[q] * x[q];
            }
            const T z = SQRT(SQRT(ni / nx));
            for (int q = 0; q < 9; ++q) {
                xn[q] = (T)0.5 * (z * x[q] + cof[q] / z);
                const T d = xn[q] > x[q] ? xn[q] - x[q] : x[q] - xn[q];
                change = d > change ? d : change;
                x[q] = xn[q];
            }
            if (last) break;
            last = change < c->tol;
            det = SFX(cofactor)(x, cof);
        }
        for (int q = 0; q < 9; ++q) c->Ro[9 * t + q] = x[q];
        SFX(mm)(Fa, x, c->Y + 9 * t); /* Y = F_a R */
    }
    c->bad[2 * task] = nbad;
    c->bad[2 * task + 1] = first;
}

long SFX(stf_fwd)(long NT, long V, int nt, const T* F, const int64_t* a, const int64_t* o, const T* g, T tol,
                  int max_iters, T* Y, T* M, T* R, int64_t* first_bad) {
    const long tasks = tc_tasks(NT, STF_TASK);
    const size_t bytes = sizeof(int64_t) * 2 * (size_t)(tasks > 0 ? tasks : 1);
    int64_t* bad = tc_scratch(bytes);
    if (!bad) return -1;
    SFX(stf_t) c = {.F = F, .g = g, .a = a, .o = o, .Y = Y, .Mo = M, .Ro = R, .tol = tol, .max_iters = max_iters,
                    .NT = NT, .V = V, .bad = bad};
    tc_parallel(tasks, NT >= STF_PAR_MIN ? nt : 1, SFX(fwd_task), &c);
    long nbad = 0;
    *first_bad = -1;
    for (long k = 0; k < tasks; ++k) {
        if (bad[2 * k] && *first_bad < 0) *first_bad = bad[2 * k + 1];
        nbad += (long)bad[2 * k];
    }
    tc_scratch_free(bad, bytes);
    return nbad;
}

/* the tet pass of the backward: dFa_t and H_t (module doc) */
static void SFX(bwd_tet_task)(void* vc, long task) {
    const SFX(stf_t)* c = (const SFX(stf_t)*)vc;
    const long t1 = (task + 1) * STF_TASK < c->NT ? (task + 1) * STF_TASK : c->NT;
    for (long t = task * STF_TASK; t < t1; ++t) {
        const T *Fa = c->F + 9 * c->a[t], *M = c->M + 9 * t, *R = c->R + 9 * t, *G = c->G + 9 * t;
        T S[9], A[9], B[9], dX[9], X[9], P[9];
        SFX(mtm)(Fa, M, X); /* X = F_a^T M, as the forward */
        SFX(mtm)(R, X, S);  /* R^T X, symmetrized below */
        SFX(mtm)(Fa, G, A); /* dL/dR = F_a^T G */
        SFX(mtm)(R, A, B);  /* R^T dL/dR */
        const T v0 = B[7] - B[5], v1 = B[2] - B[6], v2 = B[3] - B[1];
        const T s01 = (T)0.5 * (S[1] + S[3]), s02 = (T)0.5 * (S[2] + S[6]), s12 = (T)0.5 * (S[5] + S[7]);
        const T tr = S[0] + S[4] + S[8];
        const T p00 = tr - S[0], p11 = tr - S[4], p22 = tr - S[8], p01 = -s01, p02 = -s02, p12 = -s12;
        const T c00 = p11 * p22 - p12 * p12, c01 = p02 * p12 - p01 * p22, c02 = p01 * p12 - p02 * p11;
        const T c11 = p00 * p22 - p02 * p02, c12 = p01 * p02 - p00 * p12, c22 = p00 * p11 - p01 * p01;
        const T inv = (T)1 / (p00 * c00 + p01 * c01 + p02 * c02);
        const T w0 = (c00 * v0 + c01 * v1 + c02 * v2) * inv, w1 = (c01 * v0 + c11 * v1 + c12 * v2) * inv,
                w2 = (c02 * v0 + c12 * v1 + c22 * v2) * inv;
        const T W[9] = {0, -w2, w1, w2, 0, -w0, -w1, w0, 0};
        SFX(mm)(R, W, dX); /* dL/dX = R [w]_x */
        T* H = c->H + 9 * t;
        SFX(mm)(Fa, dX, H);
        for (int q = 0; q < 9; ++q) H[q] *= (T)0.25;
        T* dFa = c->dFa + 9 * t;
        SFX(mmt)(G, R, dFa);  /* G R^T */
        SFX(mmt)(M, dX, P);   /* M dX^T */
        for (int q = 0; q < 9; ++q) dFa[q] += P[q] + H[q];
    }
}

/* the vertex pass: dF_v = sum over the incident (tet, slot) of dFa_t (slot 0) or H_t g_{t,slot} */
static void SFX(bwd_vertex_task)(void* vc, long task) {
    const SFX(stf_t)* c = (const SFX(stf_t)*)vc;
    const long v1 = (task + 1) * STF_TASK < c->V ? (task + 1) * STF_TASK : c->V;
    for (long v = task * STF_TASK; v < v1; ++v) {
        T acc[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, P[9];
        for (int64_t k = c->inc_ptr[v]; k < c->inc_ptr[v + 1]; ++k) {
            const int64_t t = c->inc[k] >> 2;
            const int s = (int)(c->inc[k] & 3);
            if (s == 0) {
                for (int q = 0; q < 9; ++q) acc[q] += c->dFa[9 * t + q];
            } else {
                SFX(mm)(c->H + 9 * t, c->g + 27 * t + 9 * (s - 1), P);
                for (int q = 0; q < 9; ++q) acc[q] += P[q];
            }
        }
        for (int q = 0; q < 9; ++q) c->gF[9 * v + q] = acc[q];
    }
}

int SFX(stf_bwd)(long NT, long V, int nt, const T* F, const int64_t* a, const int64_t* o, const T* g, const T* M,
                 const T* R, const T* G, const int64_t* inc_ptr, const int64_t* inc, T* gF) {
    const size_t bytes = sizeof(T) * 18 * (size_t)(NT > 0 ? NT : 1);
    T* scratch = tc_scratch(bytes);
    if (!scratch) return -1;
    SFX(stf_t) c = {.F = F, .g = g, .M = M, .R = R, .G = G, .a = a, .o = o, .inc_ptr = inc_ptr, .inc = inc,
                    .gF = gF, .dFa = scratch, .H = scratch + 9 * NT, .NT = NT, .V = V};
    tc_parallel(tc_tasks(NT, STF_TASK), NT >= STF_PAR_MIN ? nt : 1, SFX(bwd_tet_task), &c);
    tc_parallel(tc_tasks(V, STF_TASK), V >= STF_PAR_MIN ? nt : 1, SFX(bwd_vertex_task), &c);
    tc_scratch_free(scratch, bytes);
    return 0;
}

#endif /* TC_BODY */
