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
 * The forward writes its own row per tet (parallel over tets). The backward scatters into the
 * edges race-free without atomics or per-thread copies: the tets are processed in chunks
 * (order[chunk_start[k] .. chunk_start[k+1]]), and chunks are grouped in colors
 * (chunks color_start[c] .. color_start[c+1]) such that no two chunks of one color share an
 * edge (built once per mesh by torchconn.ops.tet.TetKernel); the chunks of one color run in
 * parallel, each sequentially.
 */
#include <stdint.h>
#include <string.h>

#define S6 (1.0 / 6.0)
#define S3 (1.0 / 3.0)

/* y = M x, y = M^T x (M row-major 9) */
#define MV(y, M, x) do { for (int _i = 0; _i < 3; _i++) \
    (y)[_i] = (M)[3*_i] * (x)[0] + (M)[3*_i+1] * (x)[1] + (M)[3*_i+2] * (x)[2]; } while (0)
#define MTV(y, M, x) do { for (int _i = 0; _i < 3; _i++) \
    (y)[_i] = (M)[_i] * (x)[0] + (M)[3+_i] * (x)[1] + (M)[6+_i] * (x)[2]; } while (0)

#define DEFINE_TET(T_, SUF)                                                                        \
/* gather the 6 oriented rotations (R or R^T) of a tet */                                         \
static inline void gather_rot_##SUF(const T_ *rot, const int64_t *ri, T_ R[6][9]) {                \
    for (int p = 0; p < 6; p++) {                                                                  \
        const T_ *src = rot + 9 * (ri[p] >> 1);                                                    \
        if (ri[p] & 1) { for (int i = 0; i < 3; i++) for (int j = 0; j < 3; j++) R[p][3*i+j] = src[3*j+i]; } \
        else { for (int q = 0; q < 9; q++) R[p][q] = src[q]; }                                     \
    }                                                                                              \
}                                                                                                  \
/* ... and its 7 θ̃ */                                                                            \
static inline void gather_##SUF(const T_ *rot, const T_ *th, const int64_t *ri, const int64_t *ti, \
                                T_ R[6][9], T_ t[7][3]) {                                          \
    gather_rot_##SUF(rot, ri, R);                                                                  \
    for (int k = 0; k < 7; k++) { const T_ *src = th + 3 * ti[k]; t[k][0] = src[0]; t[k][1] = src[1]; t[k][2] = src[2]; } \
}                                                                                                  \
                                                                                                   \
/* the regrouped Ch. 5 formula; intermediates y_c, y_d, x_b, x_c, x_d */                           \
static inline void fwd_##SUF(T_ R[6][9], T_ t[7][3], T_ out[3], T_ yc[3], T_ yd[3], T_ xb[3],      \
                             T_ xc[3], T_ xd[3]) {                                                 \
    T_ pcd0[3], pcd1[3], pdc0[3], pdc1[3], pcb[3], pdb[3], a[3], b[3];                             \
    MV(pcd0, R[5], t[4]); MV(pcd1, R[5], t[2]);                                                    \
    MTV(pdc0, R[5], t[3]); MTV(pdc1, R[5], t[1]);                                                  \
    MTV(pcb, R[3], t[0]); MTV(pdb, R[4], t[0]);                                                    \
    for (int i = 0; i < 3; i++) {                                                                  \
        yc[i] = (T_)S6 * (pcd0[i] - t[1][i]) - (T_)S3 * t[3][i] + (T_)0.5 * t[6][i];               \
        yd[i] = (T_)S6 * (t[2][i] - pdc0[i]) + (T_)S3 * t[4][i] - (T_)0.5 * t[5][i];               \
        xc[i] = (T_)S6 * (pcb[i] - pcd1[i]) + (T_)0.5 * (t[3][i] - t[6][i]);                       \
        xd[i] = (T_)S6 * (pdc1[i] - pdb[i]) - (T_)0.5 * (t[4][i] - t[5][i]);                       \
    }                                                                                              \
    MV(a, R[3], yc); MV(b, R[4], yd);                                                              \
    for (int i = 0; i < 3; i++) xb[i] = a[i] + b[i];                                               \
    for (int i = 0; i < 3; i++)                                                                    \
        out[i] = R[0][3*i] * xb[0] + R[0][3*i+1] * xb[1] + R[0][3*i+2] * xb[2]                     \
               + R[1][3*i] * xc[0] + R[1][3*i+1] * xc[1] + R[1][3*i+2] * xc[2]                     \
               + R[2][3*i] * xd[0] + R[2][3*i+1] * xd[1] + R[2][3*i+2] * xd[2];                    \
}                                                                                                  \
                                                                                                   \
void tet_dd_fwd_##SUF(const T_ *rot, const T_ *th, const int64_t *ridx, const int64_t *tidx,       \
                      T_ *out, int64_t nb, int64_t E, int64_t T, int threads) {                    \
    for (int64_t bi = 0; bi < nb; bi++) {                                                          \
        const T_ *rb = rot + bi * 9 * E, *tb = th + bi * 6 * E;                                    \
        T_ *ob = out + bi * 3 * T;                                                                 \
        _Pragma("omp parallel for schedule(static) num_threads(threads)")                          \
        for (int64_t k = 0; k < T; k++) {                                                          \
            T_ R[6][9], t[7][3], yc[3], yd[3], xb[3], xc[3], xd[3];                                \
            gather_##SUF(rb, tb, ridx + 6 * k, tidx + 7 * k, R, t);                                \
            fwd_##SUF(R, t, ob + 3 * k, yc, yd, xb, xc, xd);                                       \
        }                                                                                          \
    }                                                                                              \
}                                                                                                  \
                                                                                                   \
/* G += a b^T */                                                                                   \
static inline void outer_##SUF(T_ G[9], const T_ a[3], const T_ b[3]) {                            \
    for (int i = 0; i < 3; i++) for (int j = 0; j < 3; j++) G[3*i+j] += a[i] * b[j];               \
}                                                                                                  \
                                                                                                   \
/* one tet: recompute the forward and reverse it: gR (oriented R_p), gt (the 7 θ̃) */             \
static inline void bwd_core_##SUF(T_ R[6][9], T_ t[7][3], const T_ *g, T_ gR[6][9], T_ gt[7][3]) {  \
    T_ out[3], yc[3], yd[3], xb[3], xc[3], xd[3];                                                  \
    fwd_##SUF(R, t, out, yc, yd, xb, xc, xd);                                                      \
    memset(gR, 0, sizeof(T_) * 54);                                                                \
    outer_##SUF(gR[0], g, xb); outer_##SUF(gR[1], g, xc); outer_##SUF(gR[2], g, xd);               \
    T_ gxb[3], gxc[3], gxd[3], gyc[3], gyd[3];                                                     \
    MTV(gxb, R[0], g); MTV(gxc, R[1], g); MTV(gxd, R[2], g);                                       \
    outer_##SUF(gR[3], gxb, yc); outer_##SUF(gR[4], gxb, yd);                                      \
    MTV(gyc, R[3], gxb); MTV(gyd, R[4], gxb);                                                      \
    T_ gpcd0[3], gpdc0[3], gpcb[3], gpcd1[3], gpdc1[3], gpdb[3];                                   \
    for (int i = 0; i < 3; i++) {                                                                  \
        gpcd0[i] = (T_)S6 * gyc[i]; gpdc0[i] = -(T_)S6 * gyd[i];                                   \
        gpcb[i] = (T_)S6 * gxc[i]; gpcd1[i] = -(T_)S6 * gxc[i];                                    \
        gpdc1[i] = (T_)S6 * gxd[i]; gpdb[i] = -(T_)S6 * gxd[i];                                    \
    }                                                                                              \
    outer_##SUF(gR[5], gpcd0, t[4]); outer_##SUF(gR[5], gpcd1, t[2]);                              \
    outer_##SUF(gR[5], t[3], gpdc0); outer_##SUF(gR[5], t[1], gpdc1);                              \
    outer_##SUF(gR[3], t[0], gpcb); outer_##SUF(gR[4], t[0], gpdb);                                \
    T_ u[3], v[3];                                                                                 \
    MV(u, R[3], gpcb); MV(v, R[4], gpdb);                                                          \
    for (int i = 0; i < 3; i++) gt[0][i] = u[i] + v[i];                                            \
    MV(u, R[5], gpdc1);                                                                            \
    for (int i = 0; i < 3; i++) gt[1][i] = u[i] - (T_)S6 * gyc[i];                                 \
    MTV(u, R[5], gpcd1);                                                                           \
    for (int i = 0; i < 3; i++) gt[2][i] = u[i] + (T_)S6 * gyd[i];                                 \
    MV(u, R[5], gpdc0);                                                                            \
    for (int i = 0; i < 3; i++) gt[3][i] = u[i] - (T_)S3 * gyc[i] + (T_)0.5 * gxc[i];              \
    MTV(u, R[5], gpcd0);                                                                           \
    for (int i = 0; i < 3; i++) gt[4][i] = u[i] + (T_)S3 * gyd[i] - (T_)0.5 * gxd[i];              \
    for (int i = 0; i < 3; i++) {                                                                  \
        gt[5][i] = (T_)0.5 * (gxd[i] - gyd[i]);                                                    \
        gt[6][i] = (T_)0.5 * (gyc[i] - gxc[i]);                                                    \
    }                                                                                              \
}                                                                                                  \
                                                                                                   \
static inline void scatter_rot_##SUF(const int64_t *ri, T_ gR[6][9], T_ *grot) {                   \
    for (int p = 0; p < 6; p++) {                                                                  \
        T_ *dst = grot + 9 * (ri[p] >> 1);                                                         \
        if (ri[p] & 1) { for (int i = 0; i < 3; i++) for (int j = 0; j < 3; j++) dst[3*j+i] += gR[p][3*i+j]; } \
        else { for (int q = 0; q < 9; q++) dst[q] += gR[p][q]; }                                   \
    }                                                                                              \
}                                                                                                  \
                                                                                                   \
/* one tet, θ̃ given: gather, reverse, add into grot / gth */                                      \
static inline void bwd_tet_##SUF(const T_ *rot, const T_ *th, const int64_t *ri, const int64_t *ti, \
                                 const T_ *g, T_ *grot, T_ *gth) {                                 \
    T_ R[6][9], t[7][3], gR[6][9], gt[7][3];                                                       \
    gather_##SUF(rot, th, ri, ti, R, t);                                                           \
    bwd_core_##SUF(R, t, g, gR, gt);                                                               \
    scatter_rot_##SUF(ri, gR, grot);                                                               \
    for (int k = 0; k < 7; k++) {                                                                  \
        T_ *dst = gth + 3 * ti[k];                                                                 \
        dst[0] += gt[k][0]; dst[1] += gt[k][1]; dst[2] += gt[k][2];                                \
    }                                                                                              \
}                                                                                                  \
                                                                                                   \
void tet_dd_bwd_##SUF(const T_ *rot, const T_ *th, const T_ *gin, const int64_t *ridx,             \
                      const int64_t *tidx, const int64_t *order, const int64_t *chunk_start,       \
                      const int64_t *color_start, int64_t n_colors, T_ *grot, T_ *gth,             \
                      int64_t nb, int64_t E, int64_t T, int threads) {                             \
    memset(grot, 0, sizeof(T_) * 9 * E * nb);                                                      \
    memset(gth, 0, sizeof(T_) * 6 * E * nb);                                                       \
    for (int64_t c = 0; c < n_colors; c++) {                                                       \
        int64_t c0 = color_start[c], nc = color_start[c + 1] - c0;                                 \
        /* (batch item, chunk) pairs of one color: disjoint edges within an item, */               \
        /* disjoint memory across items */                                                         \
        _Pragma("omp parallel for schedule(dynamic, 1) num_threads(threads)")                      \
        for (int64_t w = 0; w < nb * nc; w++) {                                                    \
            int64_t bi = w / nc, ch = c0 + w % nc;                                                 \
            const T_ *rb = rot + bi * 9 * E, *tb = th + bi * 6 * E, *gb = gin + bi * 3 * T;        \
            T_ *grb = grot + bi * 9 * E, *gtb = gth + bi * 6 * E;                                  \
            for (int64_t s = chunk_start[ch]; s < chunk_start[ch + 1]; s++) {                      \
                int64_t k = order[s];                                                              \
                bwd_tet_##SUF(rb, tb, ridx + 6 * k, tidx + 7 * k, gb + 3 * k, grb, gtb);           \
            }                                                                                      \
        }                                                                                          \
    }                                                                                              \
}


/* The same with θ̃ formed in the kernel from the half transports: θ̃_ij = H_e v_e (dir 0),
 * θ̃_ji = -H_e^T v_e (dir 1), half (nb, E, 9), vec (E, 3) shared by the batch. Backward:
 * ghalf (nb, E, 9) and gvec (nb, E, 3) (per batch item, summed by the caller). */
#define DEFINE_TET_SQRT(T_, SUF)                                                                   \
static inline void theta_sqrt_##SUF(const T_ *half, const T_ *vec, const int64_t *ti, T_ t[7][3]) { \
    for (int k = 0; k < 7; k++) {                                                                  \
        int64_t e = ti[k] >> 1;                                                                    \
        const T_ *H = half + 9 * e, *v = vec + 3 * e;                                              \
        if (ti[k] & 1) { MTV(t[k], H, v); for (int i = 0; i < 3; i++) t[k][i] = -t[k][i]; }        \
        else { MV(t[k], H, v); }                                                                   \
    }                                                                                              \
}                                                                                                  \
                                                                                                   \
void tet_dds_fwd_##SUF(const T_ *rot, const T_ *half, const T_ *vec, const int64_t *ridx,          \
                       const int64_t *tidx, T_ *out, int64_t nb, int64_t E, int64_t T, int threads) { \
    for (int64_t bi = 0; bi < nb; bi++) {                                                          \
        const T_ *rb = rot + bi * 9 * E, *hb = half + bi * 9 * E;                                  \
        T_ *ob = out + bi * 3 * T;                                                                 \
        _Pragma("omp parallel for schedule(static) num_threads(threads)")                          \
        for (int64_t k = 0; k < T; k++) {                                                          \
            T_ R[6][9], t[7][3], yc[3], yd[3], xb[3], xc[3], xd[3];                                \
            gather_rot_##SUF(rb, ridx + 6 * k, R);                                                 \
            theta_sqrt_##SUF(hb, vec, tidx + 7 * k, t);                                            \
            fwd_##SUF(R, t, ob + 3 * k, yc, yd, xb, xc, xd);                                       \
        }                                                                                          \
    }                                                                                              \
}                                                                                                  \
                                                                                                   \
void tet_dds_bwd_##SUF(const T_ *rot, const T_ *half, const T_ *vec, const T_ *gin,                \
                       const int64_t *ridx, const int64_t *tidx, const int64_t *order,             \
                       const int64_t *chunk_start, const int64_t *color_start, int64_t n_colors,   \
                       T_ *grot, T_ *ghalf, T_ *gvec, int64_t nb, int64_t E, int64_t T, int threads) { \
    /* pass 1 (tets, colored chunks): grot and the gradient of every directed θ̃, gth (2E, 3) per  \
     * item, scattered as 3-vectors; pass 2 (edges): ghalf, gvec from gth, once per edge instead  \
     * of once per (tet, edge) incidence. gth lives in ghalf's first 6E entries of each item     \
     * (ghalf is 9E per item), read into registers before ghalf is written. */                   \
    memset(grot, 0, sizeof(T_) * 9 * E * nb);                                                      \
    memset(ghalf, 0, sizeof(T_) * 9 * E * nb);                                                     \
    for (int64_t c = 0; c < n_colors; c++) {                                                       \
        int64_t c0 = color_start[c], nc = color_start[c + 1] - c0;                                 \
        _Pragma("omp parallel for schedule(dynamic, 1) num_threads(threads)")                      \
        for (int64_t w = 0; w < nb * nc; w++) {                                                    \
            int64_t bi = w / nc, ch = c0 + w % nc;                                                 \
            const T_ *rb = rot + bi * 9 * E, *hb = half + bi * 9 * E, *gb = gin + bi * 3 * T;      \
            T_ *grb = grot + bi * 9 * E, *gth = ghalf + bi * 9 * E;                                \
            for (int64_t s = chunk_start[ch]; s < chunk_start[ch + 1]; s++) {                      \
                int64_t k = order[s];                                                              \
                const int64_t *ri = ridx + 6 * k, *ti = tidx + 7 * k;                              \
                T_ R[6][9], t[7][3], gR[6][9], gt[7][3];                                           \
                gather_rot_##SUF(rb, ri, R);                                                       \
                theta_sqrt_##SUF(hb, vec, ti, t);                                                  \
                bwd_core_##SUF(R, t, gb + 3 * k, gR, gt);                                          \
                scatter_rot_##SUF(ri, gR, grb);                                                    \
                for (int q = 0; q < 7; q++) {                                                      \
                    T_ *d = gth + 3 * ti[q];                                                       \
                    d[0] += gt[q][0]; d[1] += gt[q][1]; d[2] += gt[q][2];                          \
                }                                                                                  \
            }                                                                                      \
        }                                                                                          \
    }                                                                                              \
    for (int64_t bi = 0; bi < nb; bi++) {                                                          \
        const T_ *hb = half + bi * 9 * E;                                                          \
        T_ *ghb = ghalf + bi * 9 * E, *gvb = gvec + bi * 3 * E;                                    \
        /* edge e reads gth[6e .. 6e+6) and writes ghalf[9e .. 9e+9): in place from the last     \
         * edge down, every read of edge e precedes the writes that could overlap it (9e >= 6e), \
         * so this pass is sequential per item (it is O(E), memory-bound, small next to pass 1) */ \
        for (int64_t e = E - 1; e >= 0; e--) {                                                     \
            const T_ *H = hb + 9 * e, *v = vec + 3 * e;                                            \
            T_ gp[3], gm[3], u[3], w[3];                                                           \
            for (int i = 0; i < 3; i++) { gp[i] = ghb[6 * e + i]; gm[i] = ghb[6 * e + 3 + i]; }    \
            /* θ̃_ij = H v: dH += gp v^T, dv += H^T gp; θ̃_ji = -H^T v: dH -= v gm^T, dv -= H gm */ \
            MTV(u, H, gp); MV(w, H, gm);                                                           \
            T_ *gH = ghb + 9 * e;                                                                  \
            for (int i = 0; i < 3; i++) for (int j = 0; j < 3; j++)                                \
                gH[3*i+j] = gp[i] * v[j] - v[i] * gm[j];                                           \
            for (int i = 0; i < 3; i++) gvb[3 * e + i] = u[i] - w[i];                              \
        }                                                                                          \
    }                                                                                              \
}

DEFINE_TET(float, f32)
DEFINE_TET(double, f64)
DEFINE_TET_SQRT(float, f32)
DEFINE_TET_SQRT(double, f64)
