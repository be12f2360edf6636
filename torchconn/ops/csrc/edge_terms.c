/* Matched edge terms of a frame field: the value and the gradient of
 *
 *     L = sum_e w_e (s_a a_e + s_d d2_e),   d2_e = max(|F_i g_e - F_j|^2, 0) = max(6 - 2 <F_i g_e, F_j>, 0),
 *     a_e = 2 asin(min(sqrt(d2_e + eps^2) / (2 sqrt 2), h_max))   (h_max = 1 - max(1e-12, dtype eps))
 *
 * over the edges e = (i, j) with fixed matchings g_e (elements of the octahedral group, given
 * by their index into torchconn.frames.octahedral.group()), the objective of the quality paths
 * (torchconn/frames/refine.py). The CPU kernels of the custom ops torchconn::matched_edge_terms
 * and torchconn::matched_edge_terms_backward (torchconn/ops/edge_terms.py, which holds the
 * generic torch formulas these loops must equal).
 *
 * Layout: frames (B, V, 3, 3) row-major with the axes as columns; edges (E, 2) int64;
 * match (E,) int64 in [0, 24); group (24, 3, 3) in double; w (E,) or NULL (all 1).
 * The products with g are signed permutations of columns: (X g)[r][c] = X[r][perm[c]] sign[c].
 *
 * Backward: dL/dF_i = k_e (-2 F_j g^T), dL/dF_j = k_e (-2 F_i g) with
 * k_e = grad w_e (s_a / (2 sqrt 2 r sqrt(1 - h^2)) + s_d) (the derivative of the clamps is not
 * taken: the same formula as the generic backward). Scatters go to per-thread buffers (thread 0
 * writes the output itself) summed at the end: no atomics, the same result for any schedule of
 * the edges among the threads (each buffer's sum order is the edge order).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>
#include <omp.h>

#ifndef TC_BODY
#define TC_BODY

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

/* out (B,) = L of every batch item. Returns 0, -1 (group table), -3 (an index out of range). */
int SFX(edge_terms_fwd)(long B, long E, long V, int nt, const T* F, const int64_t* edges, const int64_t* match,
                        const double* group, const T* w, double s_a, double s_d, double eps, double h_max, double* out) {
    int perm[24][3];
    double sign[24][3];
    if (et_setup(group, perm, sign, &nt)) return -1;
    int bad = 0;
    for (long b = 0; b < B; ++b) {
        const T* Fb = F + 9 * V * b;
        double acc = 0.0;
#pragma omp parallel for num_threads(nt) schedule(static) reduction(+ : acc) reduction(| : bad)
        for (long e = 0; e < E; ++e) {
            T Ag[9];
            const T* Bm;
            double d2, r, h;
            if (SFX(et_parts)(Fb, V, edges, match, e, (const int (*)[3])perm, (const double (*)[3])sign, eps, h_max,
                              Ag, &Bm, &d2, &r, &h)) { bad |= 1; continue; }
            double t = s_a * 2.0 * asin(h) + s_d * d2;
            acc += w ? (double)w[e] * t : t;
        }
        out[b] = acc;
    }
    return bad ? -3 : 0;
}

/* gF (B, V, 3, 3) = grad[b] dL/dF; work: (nt - 1) V 9 values of scratch. Returns as the forward. */
int SFX(edge_terms_bwd)(long B, long E, long V, int nt, const T* F, const int64_t* edges, const int64_t* match,
                        const double* group, const T* w, double s_a, double s_d, double eps, double h_max, const double* grad,
                        T* gF, T* work) {
    int perm[24][3];
    double sign[24][3];
    if (et_setup(group, perm, sign, &nt)) return -1;
    int bad = 0;
    const double c0 = 1.0 / (2.0 * sqrt(2.0));
    for (long b = 0; b < B; ++b) {
        const T* Fb = F + 9 * V * b;
        T* out = gF + 9 * V * b;
        const double gb = grad[b];
#pragma omp parallel num_threads(nt) reduction(| : bad)
        {
            int tid = omp_get_thread_num();
            int n_thr = omp_get_num_threads();
            T* acc = tid == 0 ? out : work + 9 * V * (long)(tid - 1);
            memset(acc, 0, sizeof(T) * 9 * V);
            /* contiguous blocks of edges per thread (schedule(static) without a chunk) */
            long lo = E * tid / n_thr, hi = E * (tid + 1) / n_thr;
            for (long e = lo; e < hi; ++e) {
                T Ag[9];
                const T* Bm;
                double d2, r, h;
                if (SFX(et_parts)(Fb, V, edges, match, e, (const int (*)[3])perm, (const double (*)[3])sign, eps, h_max,
                                  Ag, &Bm, &d2, &r, &h)) { bad |= 1; continue; }
                double k = -2.0 * gb * (s_a * c0 / (r * sqrt(1.0 - h * h)) + s_d);
                if (w) k *= (double)w[e];
                const T kt = (T)k;
                const int* p = perm[match[e]];
                const double* sg = sign[match[e]];
                T* gi = acc + 9 * edges[2 * e];
                T* gj = acc + 9 * edges[2 * e + 1];
                for (int rr = 0; rr < 3; ++rr)
                    for (int c = 0; c < 3; ++c) {
                        /* (F_j g^T)[rr][perm[c]] = F_j[rr][c] sign[c] */
                        gi[3 * rr + p[c]] += kt * (Bm[3 * rr + c] * (T)sg[c]);
                        gj[3 * rr + c] += kt * Ag[3 * rr + c];
                    }
            }
#pragma omp barrier
            if (n_thr > 1) {
#pragma omp for schedule(static)
                for (long q = 0; q < 9 * V; ++q) {
                    T s = out[q];
                    for (int t = 1; t < n_thr; ++t) s += work[9 * V * (long)(t - 1) + q];
                    out[q] = s;
                }
            }
        }
    }
    return bad ? -3 : 0;
}

#endif
