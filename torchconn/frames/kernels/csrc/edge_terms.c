/* Matched edge terms of a frame field: the value and the gradient of
 *
 *     L = sum_e w_e (s_a a_e + s_d d2_e),   d2_e = max(|F_i g_e - F_j|^2, 0) = max(6 - 2 <F_i g_e, F_j>, 0),
 *     a_e = 2 asin(min(sqrt(d2_e + eps^2) / (2 sqrt 2), h_max))   (h_max = 1 - max(1e-12, dtype eps))
 *
 * over the edges e = (i, j) with fixed matchings g_e (elements of the octahedral group, given
 * by their index into torchconn.frames.octahedral.group()), the objective of the quality paths
 * (torchconn/frames/quality_paths.py). The CPU kernels of the custom ops torchconn::matched_edge_terms
 * and torchconn::matched_edge_terms_backward (torchconn/frames/kernels/edge_terms.py, which holds the
 * generic torch formulas these loops must equal).
 *
 * Layout: frames (B, V, 3, 3) row-major with the axes as columns; edges (E, 2) int64;
 * match (E,) int64 in [0, 24); group (24, 3, 3) in double; w (E,) or NULL (all 1).
 * The products with g are signed permutations of columns: (X g)[r][c] = X[r][perm[c]] sign[c].
 *
 * Backward: dL/dF_i = k_e (-2 F_j g^T), dL/dF_j = k_e (-2 F_i g) with
 * k_e = grad w_e (s_a / (2 sqrt 2 r sqrt(1 - h^2)) + s_d) (the derivative of the clamps is not
 * taken: the same formula as the generic backward). Scatters go to nt buffers, one per
 * contiguous stripe of edges (stripe 0 writes the output itself), summed at the end in stripe
 * order: no atomics, the same result for any schedule of the stripes among the threads.
 * The forward's sum is per task (runs of edges whose length depends on E only), the partial
 * sums added in task order: the same value for any number of threads. Parallel loops are tasks of the pool (pool.c).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#define TC_POOL_CLIENT
#include "pool.c" /* tc_parallel */

#ifndef TC_BODY
#define TC_BODY

/* edges per task (at least; the forward uses at most ET_MAX_TASKS tasks, one partial sum each) */
#define ET_TASK 4096L
#define ET_MAX_TASKS 4096L

/* group table -> (perm, sign): g[perm[c]][c] = sign[c]; -1 when an entry is not a signed
 * permutation matrix. Also clamps the thread count to [1, 64]. */
static int et_setup(const double* g, int perm[24][3], double sign[24][3], int* nt) {
    if (*nt < 1) *nt = 1;
    if (*nt > 64) *nt = 64;
    for (int k = 0; k < 24; ++k)
        for (int c = 0; c < 3; ++c) {
            int n = 0;
            for (int r = 0; r < 3; ++r) {
                double v = g[9 * k + 3 * r + c];
                if (v > 0.5 || v < -0.5) { perm[k][c] = r; sign[k][c] = v > 0 ? 1.0 : -1.0; ++n; }
            }
            if (n != 1) return -1;
        }
    return 0;
}

#define T float
#define SFX(n) n##_f32
#include __FILE__
#undef T
#undef SFX
#define T double
#define SFX(n) n##_f64
#include __FILE__
#undef T
#undef SFX

#else /* ------------------------------------------------------------------ body, T = float | double */

/* Per-edge parts: Ag = F_i g (9), d2, r, h; returns 0, or 1 on a bad index. */
static inline int SFX(et_parts)(const T* F, long V, const int64_t* edges, const int64_t* match, long e,
                                const int perm[24][3], const double sign[24][3], double eps, double h_max,
                                T* Ag, const T** Bp, double* d2, double* r, double* h) {
    int64_t i = edges[2 * e], j = edges[2 * e + 1], m = match[e];
    if (i < 0 || i >= V || j < 0 || j >= V || m < 0 || m >= 24) return 1;
    const T* A = F + 9 * i;
    const T* B = F + 9 * j;
    double dot = 0.0;
    for (int rr = 0; rr < 3; ++rr)
        for (int c = 0; c < 3; ++c) {
            T v = A[3 * rr + perm[m][c]] * (T)sign[m][c];
            Ag[3 * rr + c] = v;
            dot += (double)v * (double)B[3 * rr + c];
        }
    double dd = 6.0 - 2.0 * dot;
    *d2 = dd > 0.0 ? dd : 0.0;
    *r = sqrt(*d2 + eps * eps);
    double hh = *r / (2.0 * sqrt(2.0));
    *h = hh < h_max ? hh : h_max;
    *Bp = B;
    return 0;
}

/* the arguments of one batch item's loops */
typedef struct {
    const T* F;
    const int64_t *edges, *match;
    const int (*perm)[3];
    const double (*sign)[3];
    const T* w;
    long E, V;
    int nt;
    double s_a, s_d, eps, h_max, gb;
    long task_len;  /* forward: edges per task */
    double* part;   /* forward: one partial sum per task */
    T *out, *work; /* backward: stripe 0 writes out, stripe t > 0 work + 9 V (t - 1) */
    int bad;
} SFX(et_t);

static void SFX(fwd_task)(void* vc, long task) {
    SFX(et_t)* c = (SFX(et_t)*)vc;
    const long e0 = task * c->task_len, e1 = e0 + c->task_len < c->E ? e0 + c->task_len : c->E;
    double acc = 0.0;
    int bad = 0;
    for (long e = e0; e < e1; ++e) {
        T Ag[9];
        const T* Bm;
        double d2, r, h;
        if (SFX(et_parts)(c->F, c->V, c->edges, c->match, e, c->perm, c->sign, c->eps, c->h_max,
                          Ag, &Bm, &d2, &r, &h)) { bad = 1; continue; }
        double t = c->s_a * 2.0 * asin(h) + c->s_d * d2;
        acc += c->w ? (double)c->w[e] * t : t;
    }
    c->part[task] = acc;
    if (bad) __atomic_store_n(&c->bad, 1, __ATOMIC_RELAXED);
}

/* out (B,) = L of every batch item. Returns 0, -1 (group table), -3 (an index out of range). */
int SFX(edge_terms_fwd)(long B, long E, long V, int nt, const T* F, const int64_t* edges, const int64_t* match,
                        const double* group, const T* w, double s_a, double s_d, double eps, double h_max, double* out) {
    int perm[24][3];
    double sign[24][3];
    if (et_setup(group, perm, sign, &nt)) return -1;
    const long task_len = E > ET_TASK * ET_MAX_TASKS ? tc_tasks(E, ET_MAX_TASKS) : ET_TASK;
    const long ntask = tc_tasks(E, task_len);
    double part[ET_MAX_TASKS];
    int bad = 0;
    for (long b = 0; b < B; ++b) {
        SFX(et_t) c = {.F = F + 9 * V * b, .edges = edges, .match = match, .perm = (const int (*)[3])perm,
                       .sign = (const double (*)[3])sign, .w = w, .E = E, .V = V, .nt = nt, .s_a = s_a,
                       .s_d = s_d, .eps = eps, .h_max = h_max, .task_len = task_len, .part = part};
        tc_parallel(ntask, nt, SFX(fwd_task), &c);
        double acc = 0.0;
        for (long k = 0; k < ntask; ++k) acc += part[k];
        out[b] = acc;
        bad |= c.bad;
    }
    return bad ? -3 : 0;
}

/* stripe t of the edges (E t / nt .. E (t + 1) / nt) scattered into its buffer */
static void SFX(bwd_stripe)(void* vc, long t) {
    SFX(et_t)* c = (SFX(et_t)*)vc;
    const double c0 = 1.0 / (2.0 * sqrt(2.0));
    const long V = c->V;
    T* acc = t == 0 ? c->out : c->work + 9 * V * (t - 1);
    memset(acc, 0, sizeof(T) * 9 * V);
    int bad = 0;
    const long lo = c->E * t / c->nt, hi = c->E * (t + 1) / c->nt;
    for (long e = lo; e < hi; ++e) {
        T Ag[9];
        const T* Bm;
        double d2, r, h;
        if (SFX(et_parts)(c->F, V, c->edges, c->match, e, c->perm, c->sign, c->eps, c->h_max,
                          Ag, &Bm, &d2, &r, &h)) { bad = 1; continue; }
        double k = -2.0 * c->gb * (c->s_a * c0 / (r * sqrt(1.0 - h * h)) + c->s_d);
        if (c->w) k *= (double)c->w[e];
        const T kt = (T)k;
        const int* p = c->perm[c->match[e]];
        const double* sg = c->sign[c->match[e]];
        T* gi = acc + 9 * c->edges[2 * e];
        T* gj = acc + 9 * c->edges[2 * e + 1];
        for (int rr = 0; rr < 3; ++rr)
            for (int cc = 0; cc < 3; ++cc) {
                /* (F_j g^T)[rr][perm[c]] = F_j[rr][c] sign[c] */
                gi[3 * rr + p[cc]] += kt * (Bm[3 * rr + cc] * (T)sg[cc]);
                gj[3 * rr + cc] += kt * Ag[3 * rr + cc];
            }
    }
    if (bad) __atomic_store_n(&c->bad, 1, __ATOMIC_RELAXED);
}

/* entries q of the output: the sum of the nt stripe buffers, in stripe order; task: ET_TASK * 9 */
static void SFX(bwd_sum)(void* vc, long task) {
    SFX(et_t)* c = (SFX(et_t)*)vc;
    const long n = 9 * c->V, q1 = (task + 1) * 9 * ET_TASK < n ? (task + 1) * 9 * ET_TASK : n;
    for (long q = task * 9 * ET_TASK; q < q1; ++q) {
        T s = c->out[q];
        for (int t = 1; t < c->nt; ++t) s += c->work[n * (long)(t - 1) + q];
        c->out[q] = s;
    }
}

/* gF (B, V, 3, 3) = grad[b] dL/dF; work: (nt - 1) V 9 values of scratch. Returns as the forward. */
int SFX(edge_terms_bwd)(long B, long E, long V, int nt, const T* F, const int64_t* edges, const int64_t* match,
                        const double* group, const T* w, double s_a, double s_d, double eps, double h_max, const double* grad,
                        T* gF, T* work) {
    int perm[24][3];
    double sign[24][3];
    if (et_setup(group, perm, sign, &nt)) return -1;
    int bad = 0;
    for (long b = 0; b < B; ++b) {
        SFX(et_t) c = {.F = F + 9 * V * b, .edges = edges, .match = match, .perm = (const int (*)[3])perm,
                       .sign = (const double (*)[3])sign, .w = w, .E = E, .V = V, .nt = nt, .s_a = s_a,
                       .s_d = s_d, .eps = eps, .h_max = h_max, .gb = grad[b], .out = gF + 9 * V * b,
                       .work = work};
        tc_parallel(nt, nt, SFX(bwd_stripe), &c);
        if (nt > 1) tc_parallel(tc_tasks(9 * V, 9 * ET_TASK), nt, SFX(bwd_sum), &c);
        bad |= c.bad;
    }
    return bad ? -3 : 0;
}

#endif
