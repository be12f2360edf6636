/* Fused value-and-gradient kernel of the frame-field loss terms smooth, tie, flat, torsion, dirichlet
 * (torchconn/frames/loss.py FrameFieldLoss; the CPU kernel of the custom ops torchconn::frame_loss and
 * torchconn::frame_loss_backward declared in torchconn/frames/kernels/frame_loss.py; issues 6, 11, 30).
 *
 * One sweep over the edges, one over the faces, one more over the edges: every per-element
 * 3x3 product is formed in registers, gradients are computed in the same sweep as the values
 * (the terms are scalar means, so their gradients are known in the forward pass), and scatters
 * go to buffers, one per stripe of the elements (nt contiguous stripes, each a task of the pool,
 * pool.c; stripe 0 writes the outputs), summed in stripe order at the end (no atomics; the
 * same result for any schedule of the stripes among the threads).
 *
 * Conventions (docs/architecture.md): R (E,3,3) maps coordinates at v_j to v_i for canonical
 * edges (i<j); frames (V,3,3) have the axes as columns; faces [a<b<c] with canonical edges
 * ab, bc, ac (fidx (F,3)); the octahedral group table (24,9) is torchconn.octahedral.group()
 * (identity first), matched with "first maximal score" like octahedral._best_element.
 *
 * Terms (rho(d2) = d2 for power 2, else (d2 + eps^2)^(power/2) - eps^power):
 *   smooth  = mean_e rho(|R_e - I|^2)
 *   tie     = mean_e rho(|F_i R_e - F_j h_e|^2),  h_e = argmax_h tr(h^T F_j^T F_i R_e)
 *   flat    = mean_f |H_f - g_f|^2,  H_f = R_ab R_bc R_ac^T,  g_f = argmax_g tr(g^T H_f)
 *   torsion = mean_f |Th_f|^2 / area_f,  Th_f = t_ab + M_ab t_bc - t_ac  (every face, through the
 *             matchings: M_ij = R_ij h_ij^T carries F_i onto F_j as labeled),
 *             t_ij = F_i^T sqrt(F_i M_ij F_j^T) (v_j - v_i)
 *   dirichlet = mean_e |F_i g_e - F_j|^2,  g_e = argmax_g tr(g^T F_i^T F_j)
 * and, on request, the flags of the regular faces (g_f = I), the mask of the dnabla term.
 * sqrt of a rotation A with angle < pi: I + (A - A^T)/(4c) + (A + A^T - 2I)/(4(1+c)),
 * c = cos(angle/2) = sqrt(1 + tr A)/2 (the matched residual F_i M_ij F_j^T of a rotation field has
 * an angle of at most ~63 degrees, the covering radius of O: c >= 0.85).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define TC_POOL_CLIENT
#include "pool.c" /* tc_parallel */

#ifndef TC_BODY
#define TC_BODY

#if defined(__GNUC__) && !defined(__clang__)
/* The lane loops have no control flow only if GCC if-converts the selects of the scores, which it
 * does for floating-point operations under -fno-trapping-math (no traps are enabled here; the
 * option changes no value); jump threading and sinking would move operations into branches (as
 * in csrc/so3.c). Popped at the end of the file. */
#pragma GCC push_options
#pragma GCC optimize("no-thread-jumps", "no-tree-sink", "no-trapping-math")
#endif

/* entries per task of the buffer sums */
#define FL_TASK 65536L

/* group table -> (perm, sign): g[perm[c]][c] = sign[c] */
static void group_perm(const double* g, int perm[24][3], double sign[24][3]) {
    for (int k = 0; k < 24; ++k)
        for (int c = 0; c < 3; ++c)
            for (int r = 0; r < 3; ++r) {
                double v = g[9 * k + 3 * r + c];
                if (v > 0.5 || v < -0.5) { perm[k][c] = r; sign[k][c] = v; }
            }
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

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC pop_options
#endif

#else /* ------------------------------------------------------------------ body, T = float | double */

/* C = A B (row-major 3x3) */
static inline void SFX(mm)(const T* A, const T* B, T* C) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}
/* C = A^T B */
static inline void SFX(mtm)(const T* A, const T* B, T* C) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[i] * B[j] + A[3 + i] * B[3 + j] + A[6 + i] * B[6 + j];
}
/* C = A B^T */
static inline void SFX(mmt)(const T* A, const T* B, T* C) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[3 * i] * B[3 * j] + A[3 * i + 1] * B[3 * j + 1] + A[3 * i + 2] * B[3 * j + 2];
}

/* argmax_k tr(g_k^T M), first index on ties: the 24 scores written out for the group order of
 * torchconn.octahedral.group() (checked against the table passed in, see frame_loss). A macro on
 * the nine entries M[0..8] of a local array (not a function taking its address: in a vectorized
 * lane loop the array then stays in registers), selects only (no branch) */
#define FL_BEST(best, M)                                                                          \
    do {                                                                                          \
        T bs_ = + M[0] + M[4] + M[8];                                                             \
        best = 0;                                                                                 \
        FL_S(best, 1, + M[0] - M[4] - M[8]) FL_S(best, 2, - M[0] + M[4] - M[8]) FL_S(best, 3, - M[0] - M[4] + M[8])   \
        FL_S(best, 4, + M[0] + M[7] - M[5]) FL_S(best, 5, + M[0] - M[7] + M[5]) FL_S(best, 6, - M[0] + M[7] + M[5])   \
        FL_S(best, 7, - M[0] - M[7] - M[5]) FL_S(best, 8, + M[3] + M[1] - M[8]) FL_S(best, 9, + M[3] - M[1] + M[8])   \
        FL_S(best, 10, - M[3] + M[1] + M[8]) FL_S(best, 11, - M[3] - M[1] - M[8]) FL_S(best, 12, + M[3] + M[7] + M[2]) \
        FL_S(best, 13, + M[3] - M[7] - M[2]) FL_S(best, 14, - M[3] + M[7] - M[2]) FL_S(best, 15, - M[3] - M[7] + M[2]) \
        FL_S(best, 16, + M[6] + M[1] + M[5]) FL_S(best, 17, + M[6] - M[1] - M[5]) FL_S(best, 18, - M[6] + M[1] - M[5]) \
        FL_S(best, 19, - M[6] - M[1] + M[5]) FL_S(best, 20, + M[6] + M[4] - M[2]) FL_S(best, 21, + M[6] - M[4] + M[2]) \
        FL_S(best, 22, - M[6] + M[4] + M[2]) FL_S(best, 23, - M[6] - M[4] - M[2])                              \
    } while (0)
#define FL_S(best, k, expr) { T s_ = expr; int c_ = s_ > bs_; best = c_ ? (k) : best; bs_ = c_ ? s_ : bs_; }

static inline int SFX(best)(const T* M) {
    int best;
    FL_BEST(best, M);
    return best;
}

static inline double SFX(rho)(double d2, double p, double eps) {
    if (p == 2.0) return d2;
    if (p == 1.0) return sqrt(d2 + eps * eps) - eps;
    return pow(d2 + eps * eps, 0.5 * p) - pow(eps, p);
}
static inline double SFX(drho)(double d2, double p, double eps) {
    if (p == 2.0) return 1.0;
    if (p == 1.0) return 0.5 / sqrt(d2 + eps * eps);
    return 0.5 * p * pow(d2 + eps * eps, 0.5 * p - 1.0);
}

/* S = sqrt(A) (see the header), c returned */
static inline T SFX(sqrt_rot)(const T* A, T* S) {
    T tr = A[0] + A[4] + A[8];
    T c = (T)0.5 * sqrt(fmax(1.0 + (double)tr, 1e-30));
    T a = (T)0.25 / c, b = (T)0.25 / ((T)1 + c);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            T an = A[3 * i + j] - A[3 * j + i], sy = A[3 * i + j] + A[3 * j + i] - (i == j ? (T)2 : (T)0);
            S[3 * i + j] = (i == j ? (T)1 : (T)0) + a * an + b * sy;
        }
    return c;
}

/* gA from gS for S = sqrt(A) */
static inline void SFX(sqrt_rot_back)(const T* A, T c, const T* gS, T* gA) {
    T a = (T)0.25 / c, b = (T)0.25 / ((T)1 + c);
    T da = -(T)0.25 / (c * c), db = -(T)0.25 / (((T)1 + c) * ((T)1 + c));
    T dot_an = 0, dot_sy = 0;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            T an = A[3 * i + j] - A[3 * j + i], sy = A[3 * i + j] + A[3 * j + i] - (i == j ? (T)2 : (T)0);
            dot_an += gS[3 * i + j] * an;
            dot_sy += gS[3 * i + j] * sy;
        }
    T gt = (da * dot_an + db * dot_sy) / ((T)8 * c);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            gA[3 * i + j] = a * (gS[3 * i + j] - gS[3 * j + i]) + b * (gS[3 * i + j] + gS[3 * j + i]) + (i == j ? gt : (T)0);
}

/* out[k] += priv[1][k] + ... + priv[nt - 1][k] (in that order) */
typedef struct {
    T* out;
    T* const* priv;
    int nt;
    long n;
} SFX(sum_t);

static void SFX(sum_task)(void* vc, long task) {
    const SFX(sum_t)* c = (const SFX(sum_t)*)vc;
    const long k1 = (task + 1) * FL_TASK < c->n ? (task + 1) * FL_TASK : c->n;
    for (long k = task * FL_TASK; k < k1; ++k) {
        T s = c->out[k];
        for (int t = 1; t < c->nt; ++t) s += c->priv[t][k];
        c->out[k] = s;
    }
}

static void SFX(reduce_into)(T* out, T* const* priv, int nt, long n) {
    if (nt <= 1) return;
    SFX(sum_t) c = {out, priv, nt, n};
    tc_parallel(tc_tasks(n, FL_TASK), nt, SFX(sum_task), &c);
}

/* the arguments of frame_loss_one's passes; stripe t of n elements: n t / nt .. n (t + 1) / nt */
typedef struct {
    long E, V, F;
    int nt;
    const T *R, *Fr;
    const int64_t *edges, *fidx;
    const T *vec, *area;
    const int (*perm)[3];
    const T (*sign)[3];
    int do_s, do_t, do_f, do_q, do_d, do_r, grad, match;
    double power, eps;
    T ws, wt, wd, kf, kq;
    T *gR, *gF, *theta, *gtheta;
    unsigned char *hidx, *regular;
    T* bR[64];
    T* bTh[64];
    T* bF[64];
    double part[64][5];  /* per-stripe partial sums, added in stripe order afterwards */
} SFX(fl_t);

/* pass 1, stripe t of the edges: smooth, tie, match, matched solder form, dirichlet; gR rows written here */
static void SFX(pass1)(void* vc, long t) {
    SFX(fl_t)* c = (SFX(fl_t)*)vc;
    const long E = c->E, V = c->V;
    const int grad = c->grad, do_s = c->do_s, do_t = c->do_t, do_q = c->do_q, do_d = c->do_d;
    const int (*perm)[3] = c->perm;
    const T (*sign)[3] = c->sign;
    double s_smooth = 0, s_tie = 0, s_dir = 0;
    if (grad) {
        if (t > 0) memset(c->bR[t], 0, sizeof(T) * (size_t)(12 * E + 9 * V));
        else { memset(c->gF, 0, sizeof(T) * (size_t)(9 * V)); if (do_q) memset(c->gtheta, 0, sizeof(T) * (size_t)(3 * E)); }
    }
    T* gFb = c->bF[t];
    const long lo = E * t / c->nt, hi = E * (t + 1) / c->nt;
    for (long e = lo; e < hi; ++e) {
        const T* Re = c->R + 9 * e;
        T G[9];
        for (int q = 0; q < 9; ++q) G[q] = 0;
        if (do_s) {
            T D[9], d2 = 0;
            for (int q = 0; q < 9; ++q) { D[q] = Re[q] - ((q % 4) == 0 ? (T)1 : (T)0); d2 += D[q] * D[q]; }
            s_smooth += SFX(rho)(d2, c->power, c->eps);
            if (grad) {
                T k = c->ws * (T)SFX(drho)(d2, c->power, c->eps);
                for (int q = 0; q < 9; ++q) G[q] = k * D[q];
            }
        }
        const long i = c->edges[2 * e], j = c->edges[2 * e + 1];
        const T *Fi = c->Fr + 9 * i, *Fj = c->Fr + 9 * j;
        if (c->match) {
            T FiR[9], M[9], Fjh[9];
            SFX(mm)(Fi, Re, FiR);
            SFX(mtm)(Fj, FiR, M);
            const int h = SFX(best)(M);
            c->hidx[e] = (unsigned char)h;
            /* F_j h: (F_j h)[r][c] = sign[c] F_j[r][perm[c]] */
            for (int r = 0; r < 3; ++r)
                for (int cc = 0; cc < 3; ++cc) Fjh[3 * r + cc] = sign[h][cc] * Fj[3 * r + perm[h][cc]];
            if (do_t) {
                T D[9], d2 = 0;
                for (int q = 0; q < 9; ++q) { D[q] = FiR[q] - Fjh[q]; d2 += D[q] * D[q]; }
                s_tie += SFX(rho)(d2, c->power, c->eps);
                if (grad) {
                    T k = c->wt * (T)SFX(drho)(d2, c->power, c->eps), t1[9];
                    for (int q = 0; q < 9; ++q) D[q] *= k;  /* dL/d(F_i R) */
                    SFX(mtm)(Fi, D, t1);                    /* F_i^T G -> R */
                    for (int q = 0; q < 9; ++q) G[q] += t1[q];
                    SFX(mmt)(D, Re, t1);                    /* G R^T -> F_i */
                    T* bi = gFb + 9 * i;
                    T* bj = gFb + 9 * j;
                    for (int q = 0; q < 9; ++q) bi[q] += t1[q];
                    /* -(G h^T)[r][k] = -G[r][c] sign[c] for perm[c] = k  -> F_j */
                    for (int r = 0; r < 3; ++r)
                        for (int cc = 0; cc < 3; ++cc) bj[3 * r + perm[h][cc]] -= D[3 * r + cc] * sign[h][cc];
                }
            }
            if (do_q) {  /* t_e = F_i^T sqrt(A) v, A = F_i R h^T F_j^T = (F_i R)(F_j h)^T */
                T A[9], S[9], u[3];
                T* th = c->theta + 3 * e;
                const T* v = c->vec + 3 * e;
                SFX(mmt)(FiR, Fjh, A);
                SFX(sqrt_rot)(A, S);
                for (int r = 0; r < 3; ++r) u[r] = S[3 * r] * v[0] + S[3 * r + 1] * v[1] + S[3 * r + 2] * v[2];
                for (int k = 0; k < 3; ++k) th[k] = Fi[k] * u[0] + Fi[3 + k] * u[1] + Fi[6 + k] * u[2];
            }
        }
        if (do_d) {  /* |F_i g - F_j|^2, g = argmax tr(g^T F_i^T F_j) */
            T M[9], D[9], d2 = 0;
            SFX(mtm)(Fi, Fj, M);
            const int g = SFX(best)(M);
            for (int r = 0; r < 3; ++r)
                for (int cc = 0; cc < 3; ++cc) {
                    T v = sign[g][cc] * Fi[3 * r + perm[g][cc]] - Fj[3 * r + cc];
                    D[3 * r + cc] = v;
                    d2 += v * v;
                }
            s_dir += d2;
            if (grad) {
                T* bi = gFb + 9 * i;
                T* bj = gFb + 9 * j;
                for (int r = 0; r < 3; ++r)
                    for (int cc = 0; cc < 3; ++cc) {
                        T gd = c->wd * D[3 * r + cc];
                        bi[3 * r + perm[g][cc]] += sign[g][cc] * gd;
                        bj[3 * r + cc] -= gd;
                    }
            }
        }
        if (grad) for (int q = 0; q < 9; ++q) c->gR[9 * e + q] = G[q];
    }
    c->part[t][0] = s_smooth;
    c->part[t][1] = s_tie;
    c->part[t][4] = s_dir;
}

/* ---- pass 2 in blocks of FL_L faces: gathered into component-major arrays (lane l = face l of
 * the block), the formulas run as one loop over the lanes that the compiler vectorizes (the same
 * arithmetic per face as the scalar formulas, in the same order), the gradients go back per face.
 * Every block computes the holonomy terms and the torsion; a term that is off gets zero inputs
 * and weights and its results are not read. */
#ifndef FL_L
#define FL_L 16
#endif

typedef struct {
    T Rab[9][FL_L], Rbc[9][FL_L], Rac[9][FL_L];
    T tab[3][FL_L], tbc[3][FL_L], tac[3][FL_L];
    T Hab[9][FL_L];  /* the matching h_ab as a matrix */
    T ia[FL_L];      /* 1 / area */
    T gab[9][FL_L], gbc[9][FL_L], gac[9][FL_L];
    T gtab[3][FL_L], gtbc[3][FL_L], gtac[3][FL_L];
    T d2[FL_L], n2[FL_L];
    int g[FL_L];
} SFX(fblk);

/* lane loop of a face block: flat (H - g, the nearest element g), torsion; with grad the
 * gradients, kf, kq the weights of flat and torsion (2 w / F) */
#define FL_FACE_LANES(GRAD)                                                                      \
    _Pragma("omp simd")                                                                          \
    for (int l = 0; l < FL_L; ++l) {                                                             \
        T P[9], H[9], w[3], Th[3];                                                               \
        for (int i = 0; i < 3; ++i)                                                              \
            for (int j = 0; j < 3; ++j)                                                          \
                P[3 * i + j] = b->Rab[3 * i][l] * b->Rbc[j][l] + b->Rab[3 * i + 1][l] * b->Rbc[3 + j][l] \
                             + b->Rab[3 * i + 2][l] * b->Rbc[6 + j][l];                          \
        for (int i = 0; i < 3; ++i)                                                              \
            for (int j = 0; j < 3; ++j)                                                          \
                H[3 * i + j] = P[3 * i] * b->Rac[3 * j][l] + P[3 * i + 1] * b->Rac[3 * j + 1][l] \
                             + P[3 * i + 2] * b->Rac[3 * j + 2][l];                              \
        int g;                                                                                   \
        FL_BEST(g, H);                                                                           \
        T d2 = 0;                                                                                \
        for (int q = 0; q < 9; ++q) { H[q] -= g9[9 * g + q]; d2 += H[q] * H[q]; }               \
        b->d2[l] = d2;                                                                           \
        b->g[l] = g;                                                                             \
        for (int k = 0; k < 3; ++k)                                                              \
            w[k] = b->Hab[k][l] * b->tbc[0][l] + b->Hab[3 + k][l] * b->tbc[1][l] + b->Hab[6 + k][l] * b->tbc[2][l]; \
        T n2 = 0;                                                                                \
        for (int r = 0; r < 3; ++r) {                                                            \
            Th[r] = b->tab[r][l] + b->Rab[3 * r][l] * w[0] + b->Rab[3 * r + 1][l] * w[1]          \
                  + b->Rab[3 * r + 2][l] * w[2] - b->tac[r][l];                                  \
            n2 += Th[r] * Th[r];                                                                 \
        }                                                                                        \
        b->n2[l] = n2 * b->ia[l];                                                                \
        if (GRAD) {                                                                              \
            T GR[9], gT[3], y[3];                                                                \
            for (int q = 0; q < 9; ++q) H[q] *= kf;  /* G = dL/dH */                             \
            for (int i = 0; i < 3; ++i)                                                          \
                for (int j = 0; j < 3; ++j)                                                      \
                    GR[3 * i + j] = H[3 * i] * b->Rac[j][l] + H[3 * i + 1] * b->Rac[3 + j][l]     \
                                  + H[3 * i + 2] * b->Rac[6 + j][l];                             \
            const T kt = kq * b->ia[l];                                                          \
            for (int r = 0; r < 3; ++r) gT[r] = kt * Th[r];                                      \
            for (int i = 0; i < 3; ++i)                                                          \
                for (int j = 0; j < 3; ++j) {                                                    \
                    b->gab[3 * i + j][l] = GR[3 * i] * b->Rbc[3 * j][l] + GR[3 * i + 1] * b->Rbc[3 * j + 1][l] \
                                         + GR[3 * i + 2] * b->Rbc[3 * j + 2][l] + gT[i] * w[j];   \
                    b->gbc[3 * i + j][l] = b->Rab[i][l] * GR[j] + b->Rab[3 + i][l] * GR[3 + j]    \
                                         + b->Rab[6 + i][l] * GR[6 + j];                         \
                    b->gac[3 * i + j][l] = H[i] * P[j] + H[3 + i] * P[3 + j] + H[6 + i] * P[6 + j]; \
                }                                                                                \
            for (int r = 0; r < 3; ++r)                                                          \
                y[r] = b->Rab[r][l] * gT[0] + b->Rab[3 + r][l] * gT[1] + b->Rab[6 + r][l] * gT[2]; \
            for (int r = 0; r < 3; ++r) {                                                        \
                b->gtab[r][l] = gT[r];                                                           \
                b->gtac[r][l] = -gT[r];                                                          \
                b->gtbc[r][l] = b->Hab[3 * r][l] * y[0] + b->Hab[3 * r + 1][l] * y[1] + b->Hab[3 * r + 2][l] * y[2]; \
            }                                                                                    \
        }                                                                                        \
    }

/* not inlined: inlined into the face loop, gcc may no longer vectorize the lane loop */
__attribute__((noinline)) static void SFX(face_fwd)(SFX(fblk)* b, const T* g9) {
    const T kf = 0, kq = 0;
    (void)kf; (void)kq;
    FL_FACE_LANES(0)
}
__attribute__((noinline)) static void SFX(face_grad)(SFX(fblk)* b, const T* g9, T kf, T kq) {
    FL_FACE_LANES(1)
}

/* pass 2, stripe t of the faces: flat (and the regular-face flags), torsion through the matchings */
static void SFX(pass2)(void* vc, long t) {
    SFX(fl_t)* c = (SFX(fl_t)*)vc;
    const int grad = c->grad, do_f = c->do_f, do_q = c->do_q, do_r = c->do_r;
    const T* R = c->R;
    T g9[24 * 9];
    for (int k = 0; k < 24; ++k)
        for (int q = 0; q < 9; ++q) g9[9 * k + q] = (T)0;
    for (int k = 0; k < 24; ++k)
        for (int cc = 0; cc < 3; ++cc) g9[9 * k + 3 * c->perm[k][cc] + cc] = c->sign[k][cc];
    double s_flat = 0, s_tor = 0;
    T* gRb = c->bR[t];
    T* gTb = c->bTh[t];
    SFX(fblk) blk;
    SFX(fblk)* b = &blk;
    const long lo = c->F * t / c->nt, hi = c->F * (t + 1) / c->nt;
    for (long f0 = lo; f0 < hi; f0 += FL_L) {
        const int n = (int)(hi - f0 < FL_L ? hi - f0 : FL_L);
        for (int l = 0; l < FL_L; ++l) {
            const long f = f0 + (l < n ? l : 0);
            const long ab = c->fidx[3 * f], bc = c->fidx[3 * f + 1], ac = c->fidx[3 * f + 2];
            const T *Rab = R + 9 * ab, *Rbc = R + 9 * bc, *Rac = R + 9 * ac;
            for (int q = 0; q < 9; ++q) { b->Rab[q][l] = Rab[q]; b->Rbc[q][l] = Rbc[q]; b->Rac[q][l] = Rac[q]; }
            if (do_q) {
                const T *tab = c->theta + 3 * ab, *tbc = c->theta + 3 * bc, *tac = c->theta + 3 * ac;
                for (int r = 0; r < 3; ++r) { b->tab[r][l] = tab[r]; b->tbc[r][l] = tbc[r]; b->tac[r][l] = tac[r]; }
                const T* hm = g9 + 9 * c->hidx[ab];
                for (int q = 0; q < 9; ++q) b->Hab[q][l] = hm[q];
                b->ia[l] = (T)1 / c->area[f];
            } else {
                for (int r = 0; r < 3; ++r) b->tab[r][l] = b->tbc[r][l] = b->tac[r][l] = 0;
                for (int q = 0; q < 9; ++q) b->Hab[q][l] = 0;
                b->ia[l] = 0;
            }
        }
        if (grad) SFX(face_grad)(b, g9, c->kf, c->kq);
        else SFX(face_fwd)(b, g9);
        for (int l = 0; l < n; ++l) {
            const long f = f0 + l;
            if (do_f) s_flat += b->d2[l];
            if (do_q) s_tor += b->n2[l];
            if (do_r) c->regular[f] = (unsigned char)(b->g[l] == 0);
            if (grad && (do_f || do_q)) {
                const long ab = c->fidx[3 * f], bc = c->fidx[3 * f + 1], ac = c->fidx[3 * f + 2];
                T *dab = gRb + 9 * ab, *dbc = gRb + 9 * bc, *dac = gRb + 9 * ac;
                for (int q = 0; q < 9; ++q) { dab[q] += b->gab[q][l]; dbc[q] += b->gbc[q][l]; dac[q] += b->gac[q][l]; }
                if (do_q) {
                    T *eab = gTb + 3 * ab, *ebc = gTb + 3 * bc, *eac = gTb + 3 * ac;
                    for (int r = 0; r < 3; ++r) { eab[r] += b->gtab[r][l]; ebc[r] += b->gtbc[r][l]; eac[r] += b->gtac[r][l]; }
                }
            }
        }
    }
    c->part[t][2] = s_flat;
    c->part[t][3] = s_tor;
}

/* pass 3, stripe t of the edges: backward of the solder form t_ij = F_i^T sqrt((F_i R)(F_j h)^T) v */
static void SFX(pass3)(void* vc, long t) {
    SFX(fl_t)* c = (SFX(fl_t)*)vc;
    const int (*perm)[3] = c->perm;
    const T (*sign)[3] = c->sign;
    T* gFb = c->bF[t];
    const long lo = c->E * t / c->nt, hi = c->E * (t + 1) / c->nt;
    for (long e = lo; e < hi; ++e) {
        const T* gt = c->gtheta + 3 * e;
        if (gt[0] == 0 && gt[1] == 0 && gt[2] == 0) continue;
        long i = c->edges[2 * e], j = c->edges[2 * e + 1];
        const int h = c->hidx[e];
        const T *Fi = c->Fr + 9 * i, *Fj = c->Fr + 9 * j, *Re = c->R + 9 * e, *v = c->vec + 3 * e;
        T FiR[9], Fjh[9], A[9], S[9], u[3], gu[3], gS[9], gA[9], gFiR[9], t1[9];
        SFX(mm)(Fi, Re, FiR);
        for (int r = 0; r < 3; ++r)
            for (int cc = 0; cc < 3; ++cc) Fjh[3 * r + cc] = sign[h][cc] * Fj[3 * r + perm[h][cc]];
        SFX(mmt)(FiR, Fjh, A);
        T cs = SFX(sqrt_rot)(A, S);
        for (int r = 0; r < 3; ++r) u[r] = S[3 * r] * v[0] + S[3 * r + 1] * v[1] + S[3 * r + 2] * v[2];
        for (int r = 0; r < 3; ++r) gu[r] = Fi[3 * r] * gt[0] + Fi[3 * r + 1] * gt[1] + Fi[3 * r + 2] * gt[2];
        for (int r = 0; r < 3; ++r)
            for (int q = 0; q < 3; ++q) gS[3 * r + q] = gu[r] * v[q];
        SFX(sqrt_rot_back)(A, cs, gS, gA);
        SFX(mm)(gA, Fjh, gFiR);                      /* dA = d(FiR) (F_j h)^T */
        T* bi = gFb + 9 * i;
        T* bj = gFb + 9 * j;
        SFX(mtm)(gA, FiR, t1);                       /* g(F_j h) = gA^T FiR; gF_j += g(F_j h) h^T */
        for (int r = 0; r < 3; ++r)
            for (int cc = 0; cc < 3; ++cc) bj[3 * r + perm[h][cc]] += sign[h][cc] * t1[3 * r + cc];
        SFX(mmt)(gFiR, Re, t1);                      /* gF_i += gFiR R^T + u gt^T */
        for (int r = 0; r < 3; ++r)
            for (int q = 0; q < 3; ++q) bi[3 * r + q] += t1[3 * r + q] + u[r] * gt[q];
        SFX(mtm)(Fi, gFiR, t1);                      /* gR += F_i^T gFiR (own row) */
        for (int q = 0; q < 9; ++q) c->gR[9 * e + q] += t1[q];
    }
}

/* ---- passes 1 and 3 in blocks of FL_L edges (as pass 2): for power 1 or 2 (rho a square root or the
 * identity, which vectorize; another power runs the scalar passes above). Every block computes
 * every edge term; a term that is off gets weight 0 and its results are not read. */

/* C = A B, C = A^T B, C = A B^T on local 3x3 arrays (macros: no address of a lane's array is taken) */
#define FL_MM(C, A, B) for (int i_ = 0; i_ < 3; ++i_) for (int j_ = 0; j_ < 3; ++j_) \
    C[3 * i_ + j_] = A[3 * i_] * B[j_] + A[3 * i_ + 1] * B[3 + j_] + A[3 * i_ + 2] * B[6 + j_];
#define FL_MTM(C, A, B) for (int i_ = 0; i_ < 3; ++i_) for (int j_ = 0; j_ < 3; ++j_) \
    C[3 * i_ + j_] = A[i_] * B[j_] + A[3 + i_] * B[3 + j_] + A[6 + i_] * B[6 + j_];
#define FL_MMT(C, A, B) for (int i_ = 0; i_ < 3; ++i_) for (int j_ = 0; j_ < 3; ++j_) \
    C[3 * i_ + j_] = A[3 * i_] * B[3 * j_] + A[3 * i_ + 1] * B[3 * j_ + 1] + A[3 * i_ + 2] * B[3 * j_ + 2];

typedef struct {
    T R[9][FL_L], Fi[9][FL_L], Fj[9][FL_L], v[3][FL_L], gt[3][FL_L];
    int h[FL_L];
    T G[9][FL_L], gFi[9][FL_L], gFj[9][FL_L], th[3][FL_L];
    T ss[FL_L], st[FL_L], sd[FL_L];
} SFX(eblk);

/* lane l: the block's arrays into local ones */
#define FL_LOAD(X, src, n) for (int q_ = 0; q_ < n; ++q_) X[q_] = b->src[q_][l];

/* pass 1 lanes: smooth, tie (match h), the matched solder form, dirichlet; with GRAD the gradient
 * rows of R and the per-edge frame gradients. p2: power 2 (else 1); ws, wt, wd: 2 w / E */
#define FL_EDGE1_LANES(GRAD)                                                                     \
    _Pragma("omp simd")                                                                          \
    for (int l = 0; l < FL_L; ++l) {                                                             \
        T R[9], Fi[9], Fj[9], D[9], G[9], FiR[9], M[9], Gh[9], Fjh[9], A[9], gFi[9], gFj[9], t1[9]; \
        FL_LOAD(R, R, 9) FL_LOAD(Fi, Fi, 9) FL_LOAD(Fj, Fj, 9)                                   \
        T d2 = 0;                                                                                \
        for (int q = 0; q < 9; ++q) { D[q] = R[q] - ((q % 4) == 0 ? (T)1 : (T)0); d2 += D[q] * D[q]; } \
        T r1 = (T)sqrt(d2 + e2);                                                                 \
        b->ss[l] = p2 ? d2 : r1 - eps_;                                                          \
        T k = ws * (p2 ? (T)1 : (T)0.5 / r1);                                                    \
        for (int q = 0; q < 9; ++q) G[q] = k * D[q];                                             \
        FL_MM(FiR, Fi, R)                                                                        \
        FL_MTM(M, Fj, FiR)                                                                       \
        int h;                                                                                   \
        FL_BEST(h, M);                                                                           \
        b->h[l] = h;                                                                             \
        for (int q = 0; q < 9; ++q) Gh[q] = g9[9 * h + q];                                       \
        FL_MM(Fjh, Fj, Gh)                                                                       \
        d2 = 0;                                                                                  \
        for (int q = 0; q < 9; ++q) { D[q] = FiR[q] - Fjh[q]; d2 += D[q] * D[q]; }               \
        r1 = (T)sqrt(d2 + e2);                                                                   \
        b->st[l] = p2 ? d2 : r1 - eps_;                                                          \
        /* the matched solder form t = F_i^T sqrt(A) v, A = (F_i R)(F_j h)^T, sqrt in closed form */ \
        FL_MMT(A, FiR, Fjh)                                                                      \
        T c = (T)0.5 * (T)sqrt((1 + A[0] + A[4] + A[8]) > (T)1e-30 ? (1 + A[0] + A[4] + A[8]) : (T)1e-30); \
        T sa = (T)0.25 / c, sb = (T)0.25 / ((T)1 + c), u[3];                                     \
        for (int i = 0; i < 3; ++i) {                                                            \
            u[i] = 0;                                                                            \
            for (int j = 0; j < 3; ++j)                                                          \
                u[i] += ((i == j ? (T)1 : (T)0) + sa * (A[3 * i + j] - A[3 * j + i])              \
                         + sb * (A[3 * i + j] + A[3 * j + i] - (i == j ? (T)2 : (T)0))) * b->v[j][l]; \
        }                                                                                        \
        for (int i = 0; i < 3; ++i) b->th[i][l] = Fi[i] * u[0] + Fi[3 + i] * u[1] + Fi[6 + i] * u[2]; \
        /* dirichlet: |F_i g - F_j|^2, g = argmax tr(g^T F_i^T F_j) */                          \
        FL_MTM(M, Fi, Fj)                                                                        \
        int g;                                                                                   \
        FL_BEST(g, M);                                                                           \
        for (int q = 0; q < 9; ++q) Gh[q] = g9[9 * g + q];  /* now g as a matrix */              \
        FL_MM(t1, Fi, Gh)                                                                        \
        T dd = 0;                                                                                \
        for (int q = 0; q < 9; ++q) { t1[q] -= Fj[q]; dd += t1[q] * t1[q]; }                     \
        b->sd[l] = dd;                                                                           \
        if (GRAD) {                                                                              \
            T kt = wt * (p2 ? (T)1 : (T)0.5 / r1), GhT[9];                                       \
            for (int q = 0; q < 9; ++q) D[q] *= kt;  /* dL/d(F_i R) */                           \
            FL_MTM(M, Fi, D)                         /* F_i^T G -> R */                          \
            for (int q = 0; q < 9; ++q) G[q] += M[q];                                            \
            FL_MMT(gFi, D, R)                        /* G R^T -> F_i */                          \
            for (int q = 0; q < 9; ++q) GhT[q] = g9[9 * h + 3 * (q % 3) + q / 3];                \
            FL_MM(gFj, D, GhT)                       /* -(G h^T) -> F_j */                       \
            for (int q = 0; q < 9; ++q) { t1[q] *= wd; gFj[q] = -gFj[q] - t1[q]; }               \
            FL_MMT(M, t1, Gh)                        /* wd D g^T -> F_i */                       \
            for (int q = 0; q < 9; ++q) {                                                        \
                gFi[q] += M[q];                                                                  \
                b->G[q][l] = G[q]; b->gFi[q][l] = gFi[q]; b->gFj[q][l] = gFj[q];                 \
            }                                                                                    \
        }                                                                                        \
    }

__attribute__((noinline)) static void SFX(edge1_fwd)(SFX(eblk)* b, const T* g9, int p2, T e2, T eps_) {
    const T ws = 0, wt = 0, wd = 0;
    (void)ws; (void)wt; (void)wd;
    FL_EDGE1_LANES(0)
}
__attribute__((noinline)) static void SFX(edge1_grad)(SFX(eblk)* b, const T* g9, int p2, T e2, T eps_, T ws, T wt,
                                                      T wd) {
    FL_EDGE1_LANES(1)
}

/* the group as a (24, 9) table in T */
static void SFX(group9)(const SFX(fl_t)* c, T* g9) {
    for (int k = 0; k < 24; ++k)
        for (int q = 0; q < 9; ++q) g9[9 * k + q] = (T)0;
    for (int k = 0; k < 24; ++k)
        for (int cc = 0; cc < 3; ++cc) g9[9 * k + 3 * c->perm[k][cc] + cc] = c->sign[k][cc];
}

/* pass 1 in blocks (power 1 or 2), stripe t of the edges */
static void SFX(pass1v)(void* vc, long t) {
    SFX(fl_t)* c = (SFX(fl_t)*)vc;
    const long E = c->E, V = c->V;
    const int grad = c->grad, do_s = c->do_s, do_t = c->do_t, do_q = c->do_q, do_d = c->do_d;
    const int p2 = c->power == 2.0;
    const T e2 = (T)(c->eps * c->eps), eps_ = (T)c->eps;
    T g9[24 * 9];
    SFX(group9)(c, g9);
    if (grad) {
        if (t > 0) memset(c->bR[t], 0, sizeof(T) * (size_t)(12 * E + 9 * V));
        else { memset(c->gF, 0, sizeof(T) * (size_t)(9 * V)); if (do_q) memset(c->gtheta, 0, sizeof(T) * (size_t)(3 * E)); }
    }
    T* gFb = c->bF[t];
    double s_smooth = 0, s_tie = 0, s_dir = 0;
    SFX(eblk) blk;
    SFX(eblk)* b = &blk;
    const T ws = do_s ? c->ws : 0, wt = do_t ? c->wt : 0, wd = do_d ? c->wd : 0;
    const long lo = E * t / c->nt, hi = E * (t + 1) / c->nt;
    for (long e0 = lo; e0 < hi; e0 += FL_L) {
        const int n = (int)(hi - e0 < FL_L ? hi - e0 : FL_L);
        for (int l = 0; l < FL_L; ++l) {
            const long e = e0 + (l < n ? l : 0);
            const T *Re = c->R + 9 * e, *Fi = c->Fr + 9 * c->edges[2 * e], *Fj = c->Fr + 9 * c->edges[2 * e + 1];
            for (int q = 0; q < 9; ++q) { b->R[q][l] = Re[q]; b->Fi[q][l] = Fi[q]; b->Fj[q][l] = Fj[q]; }
            for (int r = 0; r < 3; ++r) b->v[r][l] = c->vec[3 * e + r];
        }
        if (grad) SFX(edge1_grad)(b, g9, p2, e2, eps_, ws, wt, wd);
        else SFX(edge1_fwd)(b, g9, p2, e2, eps_);
        for (int l = 0; l < n; ++l) {
            const long e = e0 + l;
            if (do_s) s_smooth += b->ss[l];
            if (do_t) s_tie += b->st[l];
            if (do_d) s_dir += b->sd[l];
            if (do_t || do_q) c->hidx[e] = (unsigned char)b->h[l];
            if (do_q) for (int r = 0; r < 3; ++r) c->theta[3 * e + r] = b->th[r][l];
            if (grad) {
                T* gr = c->gR + 9 * e;
                for (int q = 0; q < 9; ++q) gr[q] = b->G[q][l];
                if (do_t || do_d) {
                    T *bi = gFb + 9 * c->edges[2 * e], *bj = gFb + 9 * c->edges[2 * e + 1];
                    for (int q = 0; q < 9; ++q) { bi[q] += b->gFi[q][l]; bj[q] += b->gFj[q][l]; }
                }
            }
        }
    }
    c->part[t][0] = s_smooth;
    c->part[t][1] = s_tie;
    c->part[t][4] = s_dir;
}

/* pass 3 lanes: backward of t = F_i^T sqrt(A) v, A = (F_i R)(F_j h)^T, for the incoming gt */
#define FL_EDGE3_LANES                                                                           \
    _Pragma("omp simd")                                                                          \
    for (int l = 0; l < FL_L; ++l) {                                                             \
        T R[9], Fi[9], Fj[9], Gh[9], FiR[9], Fjh[9], A[9], gS[9], gA[9], gFiR[9], t1[9], gt[3], v[3], u[3], gu[3]; \
        FL_LOAD(R, R, 9) FL_LOAD(Fi, Fi, 9) FL_LOAD(Fj, Fj, 9) FL_LOAD(gt, gt, 3) FL_LOAD(v, v, 3) \
        const int h = b->h[l];                                                                   \
        for (int q = 0; q < 9; ++q) Gh[q] = g9[9 * h + q];                                       \
        FL_MM(FiR, Fi, R)                                                                        \
        FL_MM(Fjh, Fj, Gh)                                                                       \
        FL_MMT(A, FiR, Fjh)                                                                      \
        T c = (T)0.5 * (T)sqrt((1 + A[0] + A[4] + A[8]) > (T)1e-30 ? (1 + A[0] + A[4] + A[8]) : (T)1e-30); \
        T sa = (T)0.25 / c, sb = (T)0.25 / ((T)1 + c);                                           \
        for (int i = 0; i < 3; ++i) {                                                            \
            u[i] = 0;                                                                            \
            for (int j = 0; j < 3; ++j)                                                          \
                u[i] += ((i == j ? (T)1 : (T)0) + sa * (A[3 * i + j] - A[3 * j + i])              \
                         + sb * (A[3 * i + j] + A[3 * j + i] - (i == j ? (T)2 : (T)0))) * v[j];  \
        }                                                                                        \
        for (int r = 0; r < 3; ++r) gu[r] = Fi[3 * r] * gt[0] + Fi[3 * r + 1] * gt[1] + Fi[3 * r + 2] * gt[2]; \
        for (int r = 0; r < 3; ++r)                                                              \
            for (int q = 0; q < 3; ++q) gS[3 * r + q] = gu[r] * v[q];                            \
        /* gA from gS (sqrt_rot_back) */                                                         \
        T da = -(T)0.25 / (c * c), db = -(T)0.25 / (((T)1 + c) * ((T)1 + c)), dot_an = 0, dot_sy = 0; \
        for (int i = 0; i < 3; ++i)                                                              \
            for (int j = 0; j < 3; ++j) {                                                        \
                dot_an += gS[3 * i + j] * (A[3 * i + j] - A[3 * j + i]);                         \
                dot_sy += gS[3 * i + j] * (A[3 * i + j] + A[3 * j + i] - (i == j ? (T)2 : (T)0)); \
            }                                                                                    \
        T gtr = (da * dot_an + db * dot_sy) / ((T)8 * c);                                        \
        for (int i = 0; i < 3; ++i)                                                              \
            for (int j = 0; j < 3; ++j)                                                          \
                gA[3 * i + j] = sa * (gS[3 * i + j] - gS[3 * j + i]) + sb * (gS[3 * i + j] + gS[3 * j + i]) \
                              + (i == j ? gtr : (T)0);                                           \
        FL_MM(gFiR, gA, Fjh)                       /* dA = d(FiR) (F_j h)^T */                    \
        FL_MTM(t1, gA, FiR)                        /* g(F_j h) = gA^T FiR */                      \
        FL_MMT(A, t1, Gh)                          /* gF_j = g(F_j h) h^T */                      \
        for (int q = 0; q < 9; ++q) b->gFj[q][l] = A[q];                                         \
        FL_MMT(A, gFiR, R)                         /* gF_i = gFiR R^T + u gt^T */                \
        for (int r = 0; r < 3; ++r)                                                              \
            for (int q = 0; q < 3; ++q) b->gFi[3 * r + q][l] = A[3 * r + q] + u[r] * gt[q];       \
        FL_MTM(A, Fi, gFiR)                        /* gR += F_i^T gFiR */                         \
        for (int q = 0; q < 9; ++q) b->G[q][l] = A[q];                                           \
    }

__attribute__((noinline)) static void SFX(edge3)(SFX(eblk)* b, const T* g9) {
    FL_EDGE3_LANES
}

/* pass 3 in blocks, stripe t of the edges */
static void SFX(pass3v)(void* vc, long t) {
    SFX(fl_t)* c = (SFX(fl_t)*)vc;
    T g9[24 * 9];
    SFX(group9)(c, g9);
    T* gFb = c->bF[t];
    SFX(eblk) blk;
    SFX(eblk)* b = &blk;
    const long lo = c->E * t / c->nt, hi = c->E * (t + 1) / c->nt;
    for (long e0 = lo; e0 < hi; e0 += FL_L) {
        const int n = (int)(hi - e0 < FL_L ? hi - e0 : FL_L);
        for (int l = 0; l < FL_L; ++l) {
            const long e = e0 + (l < n ? l : 0);
            const T *Re = c->R + 9 * e, *Fi = c->Fr + 9 * c->edges[2 * e], *Fj = c->Fr + 9 * c->edges[2 * e + 1];
            for (int q = 0; q < 9; ++q) { b->R[q][l] = Re[q]; b->Fi[q][l] = Fi[q]; b->Fj[q][l] = Fj[q]; }
            for (int r = 0; r < 3; ++r) { b->v[r][l] = c->vec[3 * e + r]; b->gt[r][l] = c->gtheta[3 * e + r]; }
            b->h[l] = c->hidx[e];
        }
        SFX(edge3)(b, g9);
        for (int l = 0; l < n; ++l) {
            const long e = e0 + l;
            T *bi = gFb + 9 * c->edges[2 * e], *bj = gFb + 9 * c->edges[2 * e + 1], *gr = c->gR + 9 * e;
            for (int q = 0; q < 9; ++q) { bi[q] += b->gFi[q][l]; bj[q] += b->gFj[q][l]; gr[q] += b->G[q][l]; }
        }
    }
}

/* One item (no batch): the terms that are on (do_s smooth, do_t tie, do_f flat, do_q torsion,
 * do_d dirichlet) and, with do_r, the regular-face flags regular (F) (1 where the holonomy's
 * nearest element of O is the identity); with grad, the gradient of sum_k wts[k] term_k.
 * sums (out, 5): smooth, tie, flat, torsion, dirichlet values (0 for a term that is off). With
 * grad: gR (E,9) = sum_k wts[k] dterm_k/dR and gF (V,9) = sum_k wts[k] dterm_k/dframes
 * (overwritten). work: (nt - 1) * (9E + 3E + 9V) stripe scatter buffers (zeroed here); theta,
 * gtheta (E,3) and hidx (E) are workspaces. perm/sign: the group table as signed permutations
 * (group_perm). */
static void SFX(frame_loss_one)(long E, long V, long F, int nt,
                     const T* R, const T* Fr, const int64_t* edges, const int64_t* fidx,
                     const T* vec, const T* area, const int perm[24][3], const T sign[24][3],
                     int do_s, int do_t, int do_f, int do_q, int do_d, int do_r, int grad, double power,
                     double eps, const double* wts, double* sums, T* gR, T* gF, unsigned char* regular,
                     T* work, T* theta, T* gtheta, unsigned char* hidx) {
    grad = grad != 0;
    SFX(fl_t) c = {.E = E, .V = V, .F = F, .nt = nt, .R = R, .Fr = Fr, .edges = edges, .fidx = fidx,
                   .vec = vec, .area = area, .perm = perm, .sign = sign, .do_s = do_s, .do_t = do_t,
                   .do_f = do_f, .do_q = do_q, .do_d = do_d, .do_r = do_r, .grad = grad,
                   .match = do_t || do_q, .power = power, .eps = eps, .gR = gR, .gF = gF, .theta = theta,
                   .gtheta = gtheta, .hidx = hidx, .regular = regular};
    memset(c.part, 0, sizeof(c.part));
    /* stripe buffers: stripe 0 writes the outputs, stripe t > 0 its slice of work */
    c.bR[0] = gR; c.bTh[0] = gtheta; c.bF[0] = gF;
    for (int t = 1; t < nt; ++t) {
        T* base = work + (size_t)(t - 1) * (size_t)(12 * E + 9 * V);
        c.bR[t] = base; c.bTh[t] = base + 9 * E; c.bF[t] = base + 12 * E;
    }
    const double En = (double)(E > 0 ? E : 1), Fn = (double)(F > 0 ? F : 1);
    c.ws = (T)(grad ? wts[0] * 2.0 / En : 0);
    c.wt = (T)(grad ? wts[1] * 2.0 / En : 0);
    c.wd = (T)(grad ? wts[4] * 2.0 / En : 0);

    /* ---- pass 1: edges (smooth, tie, match, solder form, dirichlet); gR rows written here */
    const int blocked = power == 2.0 || power == 1.0;  /* rho vectorizes (a square root at most) */
    tc_parallel(nt, nt, blocked ? SFX(pass1v) : SFX(pass1), &c);

    /* ---- pass 2: faces (flat, regular flags, torsion) */
    if (do_f || do_q || do_r) {
        c.kf = (T)(grad && do_f ? wts[2] * 2.0 / Fn : 0);  /* a face block computes both: off = weight 0 */
        c.kq = (T)(grad && do_q ? wts[3] * 2.0 / Fn : 0);
        tc_parallel(nt, nt, SFX(pass2), &c);
        if (grad && (do_f || do_q)) {
            SFX(reduce_into)(gR, c.bR, nt, 9 * E);
            if (do_q) SFX(reduce_into)(gtheta, c.bTh, nt, 3 * E);
        }
    }

    /* ---- pass 3: edges, backward of the solder form t_ij = F_i^T sqrt((F_i R)(F_j h)^T) v */
    if (grad && do_q) tc_parallel(nt, nt, blocked ? SFX(pass3v) : SFX(pass3), &c);
    if (grad) SFX(reduce_into)(gF, c.bF, nt, 9 * V);

    double s[5] = {0, 0, 0, 0, 0};
    for (int t = 0; t < nt; ++t)
        for (int k = 0; k < 5; ++k) s[k] += c.part[t][k];
    sums[0] = s[0] / En;
    sums[1] = s[1] / En;
    sums[2] = s[2] / Fn;
    sums[3] = s[3] / Fn;
    sums[4] = s[4] / En;
}

/* The op torchconn::frame_loss (and its backward, torchconn::frame_loss_backward) on B items that
 * share one mesh: R (B,E,9), Fr (B,V,9), wts (B,5) (the gradient weights of each item), sums
 * (B,5), gR (B,E,9), gF (B,V,9) (with grad), regular (B,F) (with do_r); the workspaces are reused
 * item after item.
 * Options are explicit arguments (no bit flags). Returns 0, or -2 when the group table is not
 * torchconn.octahedral.group() (the written-out scores of best() assume its order). */
int SFX(frame_loss)(long B, long E, long V, long F, int nt,
                     const T* R, const T* Fr, const int64_t* edges, const int64_t* fidx,
                     const T* vec, const T* area, const double* group,
                     int do_s, int do_t, int do_f, int do_q, int do_d, int do_r, int grad, double power,
                     double eps, const double* wts, double* sums, T* gR, T* gF, unsigned char* regular,
                     T* work, T* theta, T* gtheta, unsigned char* hidx) {
    int perm[24][3];
    double sign_d[24][3];
    T sign[24][3];
    group_perm(group, perm, sign_d);
    for (int k = 0; k < 24; ++k) {
        T gk[9];
        for (int c = 0; c < 3; ++c) sign[k][c] = (T)sign_d[k][c];
        for (int q = 0; q < 9; ++q) gk[q] = (T)group[9 * k + q];
        if (SFX(best)(gk) != k) return -2;  /* the written-out scores do not match the group table */
    }
    if (nt < 1) nt = 1;
    if (nt > 64) nt = 64;
    for (long b = 0; b < B; ++b)
        SFX(frame_loss_one)(E, V, F, nt, R + 9 * E * b, Fr + 9 * V * b, edges, fidx, vec, area,
                            (const int (*)[3])perm, (const T (*)[3])sign, do_s, do_t, do_f, do_q, do_d, do_r,
                            grad, power, eps, wts + 5 * b, sums + 5 * b, grad ? gR + 9 * E * b : gR,
                            grad ? gF + 9 * V * b : gF, do_r ? regular + F * b : regular, work, theta, gtheta,
                            hidx);
    return 0;
}

#endif
