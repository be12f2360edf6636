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
 * torchconn.octahedral.group() (checked against the table passed in, see frame_loss) */
static inline int SFX(best)(const T* M) {
    int best = 0;
    T bs = -INFINITY;
#define X(k, expr) { T s_ = expr; int b_ = s_ > bs; best = b_ ? k : best; bs = b_ ? s_ : bs; }
    X(0, + M[0] + M[4] + M[8]) X(1, + M[0] - M[4] - M[8]) X(2, - M[0] + M[4] - M[8])
    X(3, - M[0] - M[4] + M[8]) X(4, + M[0] + M[7] - M[5]) X(5, + M[0] - M[7] + M[5])
    X(6, - M[0] + M[7] + M[5]) X(7, - M[0] - M[7] - M[5]) X(8, + M[3] + M[1] - M[8])
    X(9, + M[3] - M[1] + M[8]) X(10, - M[3] + M[1] + M[8]) X(11, - M[3] - M[1] - M[8])
    X(12, + M[3] + M[7] + M[2]) X(13, + M[3] - M[7] - M[2]) X(14, - M[3] + M[7] - M[2])
    X(15, - M[3] - M[7] + M[2]) X(16, + M[6] + M[1] + M[5]) X(17, + M[6] - M[1] - M[5])
    X(18, - M[6] + M[1] - M[5]) X(19, - M[6] - M[1] + M[5]) X(20, + M[6] + M[4] - M[2])
    X(21, + M[6] - M[4] + M[2]) X(22, - M[6] + M[4] + M[2]) X(23, - M[6] - M[4] - M[2])
#undef X
    return best;
}

/* rho and d rho / d d2 (power 2: the identity; power 1, the default of the method: a square root,
 * not pow, which costs ~10x as much per edge) */
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

/* pass 2, stripe t of the faces: flat (and the regular-face flags), torsion through the matchings */
static void SFX(pass2)(void* vc, long t) {
    SFX(fl_t)* c = (SFX(fl_t)*)vc;
    const int grad = c->grad, do_f = c->do_f, do_q = c->do_q, do_r = c->do_r;
    const int (*perm)[3] = c->perm;
    const T (*sign)[3] = c->sign;
    const T* R = c->R;
    double s_flat = 0, s_tor = 0;
    T* gRb = c->bR[t];
    T* gTb = c->bTh[t];
    const long lo = c->F * t / c->nt, hi = c->F * (t + 1) / c->nt;
    for (long f = lo; f < hi; ++f) {
        long ab = c->fidx[3 * f], bc = c->fidx[3 * f + 1], ac = c->fidx[3 * f + 2];
        const T *Rab = R + 9 * ab, *Rbc = R + 9 * bc, *Rac = R + 9 * ac;
        if (do_f || do_r) {
            T P[9], H[9], d2 = 0;
            SFX(mm)(Rab, Rbc, P);
            SFX(mmt)(P, Rac, H);
            int g = SFX(best)(H);
            if (do_r) c->regular[f] = (unsigned char)(g == 0);
            if (do_f) {
                for (int cc = 0; cc < 3; ++cc) H[3 * perm[g][cc] + cc] -= sign[g][cc];  /* H - g */
                for (int q = 0; q < 9; ++q) d2 += H[q] * H[q];
                s_flat += d2;
                if (grad) {
                    T GR[9], t1[9];
                    for (int q = 0; q < 9; ++q) H[q] *= c->kf;  /* G = dL/dH */
                    SFX(mm)(H, Rac, GR);                        /* G R_ac */
                    SFX(mmt)(GR, Rbc, t1);                      /* -> R_ab */
                    for (int q = 0; q < 9; ++q) gRb[9 * ab + q] += t1[q];
                    SFX(mtm)(Rab, GR, t1);                      /* -> R_bc */
                    for (int q = 0; q < 9; ++q) gRb[9 * bc + q] += t1[q];
                    SFX(mtm)(H, P, t1);                         /* G^T P -> R_ac */
                    for (int q = 0; q < 9; ++q) gRb[9 * ac + q] += t1[q];
                }
            }
        }
        if (do_q) {  /* Th = t_ab + R_ab w - t_ac, w = h_ab^T t_bc: w[k] = sign[k] t_bc[perm[k]] */
            const T *tab = c->theta + 3 * ab, *tbc = c->theta + 3 * bc, *tac = c->theta + 3 * ac;
            const int h = c->hidx[ab];
            T w[3], Th[3], n2 = 0;
            for (int k = 0; k < 3; ++k) w[k] = sign[h][k] * tbc[perm[h][k]];
            for (int r = 0; r < 3; ++r) {
                Th[r] = tab[r] + Rab[3 * r] * w[0] + Rab[3 * r + 1] * w[1] + Rab[3 * r + 2] * w[2] - tac[r];
                n2 += Th[r] * Th[r];
            }
            s_tor += n2 / c->area[f];
            if (grad) {
                T k = c->kq / c->area[f], gT[3], y[3];
                for (int r = 0; r < 3; ++r) gT[r] = k * Th[r];
                for (int r = 0; r < 3; ++r) y[r] = Rab[r] * gT[0] + Rab[3 + r] * gT[1] + Rab[6 + r] * gT[2];
                for (int r = 0; r < 3; ++r) {
                    gTb[3 * ab + r] += gT[r];
                    gTb[3 * ac + r] -= gT[r];
                    gTb[3 * bc + perm[h][r]] += sign[h][r] * y[r];  /* h R_ab^T gT */
                    for (int cc = 0; cc < 3; ++cc) gRb[9 * ab + 3 * r + cc] += gT[r] * w[cc];
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
    tc_parallel(nt, nt, SFX(pass1), &c);

    /* ---- pass 2: faces (flat, regular flags, torsion) */
    if (do_f || do_q || do_r) {
        c.kf = (T)(grad ? wts[2] * 2.0 / Fn : 0);
        c.kq = (T)(grad ? wts[3] * 2.0 / Fn : 0);
        tc_parallel(nt, nt, SFX(pass2), &c);
        if (grad && (do_f || do_q)) {
            SFX(reduce_into)(gR, c.bR, nt, 9 * E);
            if (do_q) SFX(reduce_into)(gtheta, c.bTh, nt, 3 * E);
        }
    }

    /* ---- pass 3: edges, backward of the solder form t_ij = F_i^T sqrt((F_i R)(F_j h)^T) v */
    if (grad && do_q) tc_parallel(nt, nt, SFX(pass3), &c);
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
