/* Compiled kernels for the hot path of a linearisation (docs/performance.md, section 8,
 * "The box factor compiled").
 *
 * Built with the package when a C compiler is there (setup.py: an optional extension); the
 * Python module it defines is empty: spdslam.geometry._native loads this file with ctypes and
 * calls the functions below on NumPy arrays (C-contiguous float64, int64 indices). Each
 * function is the NumPy code it replaces, written per row; the tests compare them.
 *
 * box_linearize: the inverse box factor's residual, validity and Jacobian
 * (spdslam.factors._closed_form.inverse_box_linearization, whose docstrings give the maths).
 * pose_prior, pose_between: the pose factors' residuals and Jacobians (the same module's
 * pose_prior_linearization and pose_between_linearization, through geometry.se3's functions).
 * whiten: a factor's whitened residual and Jacobian, their finiteness and ‖W r‖².
 * gram_upper: each row's JᵀJ upper triangle (row-major, i ≤ j) and Jᵀr.
 * segment_medians: the medians of consecutive segments (the association's refits).
 * scatter_add: values added into slots (H's assembly); gram_scatter: both in one pass.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>

/* The entries (I[e], J[e]) of G the box edges read: (G00, G11, G22, G02, G12). */
static const int EI[5] = {0, 1, 2, 0, 1};
static const int EJ[5] = {0, 1, 2, 2, 2};

static void rotation(const double *T, double R[3][3]);

/* One edge pair: (lower, upper) image coordinates c0 + f (b ± √Δ)/g, Δ = b² − a g (√ of
 * Δ ≤ 0 taken as 0, with derivative 0), and their derivatives by (a, b, g). */
static void edges(double a, double b, double g, double f, double c0, double value[2], double d[2][3]) {
    double delta = b * b - a * g;
    int pos = delta > 0;
    double s = pos ? sqrt(delta) : 0.0;
    double sign_lo = g < 0 ? 1.0 : -1.0;
    double inv_2s = pos ? 0.5 / s : 0.0;
    double ds0 = -g * inv_2s, ds1 = 2.0 * b * inv_2s, ds2 = -a * inv_2s;
    for (int k = 0; k < 2; ++k) {
        double sigma = k == 0 ? sign_lo : -sign_lo;
        value[k] = c0 + f * (b + sigma * s) / g;
        d[k][0] = f * sigma * ds0 / g;
        d[k][1] = f * (1.0 + sigma * ds1) / g;
        d[k][2] = f * sigma * ds2 / g - f * (b + sigma * s) / (g * g);
    }
}

/* n (pose, ellipsoid) pairs of the inverse box model.
 * q (n, 7) wxyz xyz (T_wc); P (n, 9); t (n, 3); obs (n, 4); fx, fy, cx, cy: per row with
 * stride cam_stride (0: one camera); keep (n, 4) or NULL; directions (L, 12, Q) and index
 * (n,) the landmark of each row, or directions NULL for no Jacobian.
 * Out: r (n, 4); valid (n,); J (n, 4, 6 + Q) when directions is given. */
void box_linearize(int64_t n, const double *q, const double *P, const double *t, const double *obs,
                   const double *fx, const double *fy, const double *cx, const double *cy, int64_t cam_stride,
                   const double *keep, const double *directions, const int64_t *index, int64_t Q,
                   double min_depth, double *r, uint8_t *valid, double *J) {
    const int64_t D = 6 + Q;
    for (int64_t k = 0; k < n; ++k) {
        const double *qk = q + 7 * k, *Pk = P + 9 * k, *tk = t + 3 * k;
        double R[3][3], A[3][3];
        int ok = 1, nonzero = 0;
        for (int i = 0; i < 7; ++i) ok &= isfinite(qk[i]) != 0;
        for (int i = 0; i < 4; ++i) nonzero |= qk[i] != 0.0;
        if (ok && nonzero) {
            rotation(qk, R);
        } else {
            for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j) R[i][j] = NAN;
        }
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) A[i][j] = R[j][i];
        /* m = A (t − c); S = A P Aᵀ; G = S − m mᵀ */
        double dlt[3] = {tk[0] - qk[4], tk[1] - qk[5], tk[2] - qk[6]}, m[3], AP[3][3], G[3][3];
        for (int i = 0; i < 3; ++i) m[i] = A[i][0] * dlt[0] + A[i][1] * dlt[1] + A[i][2] * dlt[2];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) AP[i][j] = A[i][0] * Pk[j] + A[i][1] * Pk[3 + j] + A[i][2] * Pk[6 + j];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                G[i][j] = AP[i][0] * R[0][j] + AP[i][1] * R[1][j] + AP[i][2] * R[2][j] - m[i] * m[j];
        double fxk = fx[cam_stride * k], fyk = fy[cam_stride * k], cxk = cx[cam_stride * k], cyk = cy[cam_stride * k];
        double u[2], v[2], du[2][3], dv[2][3];
        edges(G[0][0], G[0][2], G[2][2], fxk, cxk, u, du);
        edges(G[1][1], G[1][2], G[2][2], fyk, cyk, v, dv);
        double box[4] = {u[0], v[0], u[1], v[1]};
        /* ∂box/∂(G00, G11, G22, G02, G12) */
        double dr[4][5] = {{0}};
        dr[0][0] = du[0][0], dr[0][3] = du[0][1], dr[0][2] = du[0][2];
        dr[2][0] = du[1][0], dr[2][3] = du[1][1], dr[2][2] = du[1][2];
        dr[1][1] = dv[0][0], dr[1][4] = dv[0][1], dr[1][2] = dv[0][2];
        dr[3][1] = dv[1][0], dr[3][4] = dv[1][1], dr[3][2] = dv[1][2];
        for (int i = 0; i < 4; ++i) {
            double ki = keep ? keep[4 * k + i] : 1.0;
            r[4 * k + i] = keep ? (box[i] - obs[4 * k + i]) * ki : box[i] - obs[4 * k + i];
            if (keep)
                for (int e = 0; e < 5; ++e) dr[i][e] *= ki;
        }
        /* in front: z_c − √(a₂ᵀ P a₂) > min_depth */
        double half2 = 0.0;
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) half2 += A[2][i] * Pk[3 * i + j] * A[2][j];
        double half = half2 > 0 ? sqrt(half2) : 0.0;
        valid[k] = m[2] - half > min_depth;
        if (!directions) continue;
        /* the pose's ∂G_e/∂(ρ, ω) (5, 6) */
        double g00 = G[0][0], g11 = G[1][1], g22 = G[2][2], g01 = G[0][1], g02 = G[0][2], g12 = G[1][2];
        double dG[5][6] = {{0}};
        dG[0][0] = 2.0 * m[0], dG[1][1] = 2.0 * m[1], dG[2][2] = 2.0 * m[2];
        dG[3][0] = m[2], dG[3][2] = m[0];
        dG[4][1] = m[2], dG[4][2] = m[1];
        dG[0][4] = -2.0 * g02, dG[0][5] = 2.0 * g01;
        dG[1][3] = 2.0 * g12, dG[1][5] = -2.0 * g01;
        dG[2][3] = -2.0 * g12, dG[2][4] = 2.0 * g02;
        dG[3][3] = -g01, dG[3][4] = g00 - g22, dG[3][5] = g12;
        dG[4][3] = g22 - g11, dG[4][4] = g01, dG[4][5] = -g02;
        /* the landmark's coefficients of (dP, dt) in ∂G_e (5, 12) */
        double coef[5][12];
        for (int e = 0; e < 5; ++e) {
            const double *ai = A[EI[e]], *aj = A[EJ[e]];
            double mi = m[EI[e]], mj = m[EJ[e]];
            for (int a = 0; a < 3; ++a)
                for (int b = 0; b < 3; ++b) coef[e][3 * a + b] = ai[a] * aj[b];
            for (int c = 0; c < 3; ++c) coef[e][9 + c] = -(mj * ai[c] + mi * aj[c]);
        }
        const double *T = directions + index[k] * 12 * Q;
        double *Jk = J + k * 4 * D;
        for (int i = 0; i < 4; ++i) {
            double *row = Jk + i * D;
            for (int c = 0; c < 6; ++c) {
                double acc = 0.0;
                for (int e = 0; e < 5; ++e) acc += dr[i][e] * dG[e][c];
                row[c] = acc;
            }
            double tmp[12];
            for (int c = 0; c < 12; ++c) {
                double acc = 0.0;
                for (int e = 0; e < 5; ++e) acc += dr[i][e] * coef[e][c];
                tmp[c] = acc;
            }
            for (int c = 0; c < Q; ++c) row[6 + c] = 0.0;
            for (int l = 0; l < 12; ++l) {
                const double *Tl = T + l * Q;
                for (int c = 0; c < Q; ++c) row[6 + c] += tmp[l] * Tl[c];
            }
        }
    }
}

/* --- SE(3) in wxyz_xyz parameters (geometry.se3's NumPy functions, per row) ------------- */

/* jaxlie's float64 threshold on ‖q_xyz‖² and θ², and right_jacobian_inverse's θ below which
 * Q's coefficients take their series (se3._JAXLIE_EPS, se3._Q_SERIES). */
#define JAXLIE_EPS 1e-10
#define Q_SERIES 1e-2

static void rotation(const double *T, double R[3][3]) {
    /* se3._rotation (SciPy's Rotation.from_quat(xyzw).as_matrix(), term for term): normalised here */
    double w = T[0], x = T[1], y = T[2], z = T[3];
    double nq = sqrt(x * x + y * y + z * z + w * w);
    x /= nq, y /= nq, z /= nq, w /= nq;
    double x2 = x * x, y2 = y * y, z2 = z * z, w2 = w * w;
    double xy = x * y, zw = z * w, xz = x * z, yw = y * w, yz = y * z, xw = x * w;
    R[0][0] = x2 - y2 - z2 + w2, R[0][1] = 2 * (xy - zw), R[0][2] = 2 * (xz + yw);
    R[1][0] = 2 * (xy + zw), R[1][1] = -x2 + y2 - z2 + w2, R[1][2] = 2 * (yz - xw);
    R[2][0] = 2 * (xz - yw), R[2][1] = 2 * (yz + xw), R[2][2] = -x2 - y2 + z2 + w2;
}

static void inverse(const double *a, double *out) {  /* (q̄, −Rᵀ t) */
    double R[3][3];
    rotation(a, R);
    out[0] = a[0], out[1] = -a[1], out[2] = -a[2], out[3] = -a[3];
    for (int i = 0; i < 3; ++i) out[4 + i] = -(R[0][i] * a[4] + R[1][i] * a[5] + R[2][i] * a[6]);
}

static void compose(const double *a, const double *b, double *out) {  /* (q_a q_b, R_a t_b + t_a) */
    double R[3][3], t[3];
    rotation(a, R);
    for (int i = 0; i < 3; ++i) t[i] = R[i][0] * b[4] + R[i][1] * b[5] + R[i][2] * b[6] + a[4 + i];
    double aw = a[0], ax = a[1], ay = a[2], az = a[3], bw = b[0], bx = b[1], by = b[2], bz = b[3];
    out[0] = aw * bw - ax * bx - ay * by - az * bz;
    out[1] = aw * bx + ax * bw + ay * bz - az * by;
    out[2] = aw * by - ax * bz + ay * bw + az * bx;
    out[3] = aw * bz + ax * by - ay * bx + az * bw;
    for (int i = 0; i < 3; ++i) out[4 + i] = t[i];
}

static void hat(const double *w, double W[3][3]) {
    W[0][0] = 0.0, W[0][1] = -w[2], W[0][2] = w[1];
    W[1][0] = w[2], W[1][1] = 0.0, W[1][2] = -w[0];
    W[2][0] = -w[1], W[2][1] = w[0], W[2][2] = 0.0;
}

static void mul3(double A[3][3], double B[3][3], double C[3][3]) {
    double out[3][3];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) out[i][j] = A[i][0] * B[0][j] + A[i][1] * B[1][j] + A[i][2] * B[2][j];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) C[i][j] = out[i][j];
}

/* J_l⁻¹(ω) of SO(3) = I − ½[ω]× + c [ω]×², c = (1 − θ cos(θ/2) / (2 sin(θ/2)))/θ² (1/12 below
 * θ² = 1e-10) */
static void so3_left_jacobian_inverse(const double *w, double out[3][3]) {
    double th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    int small = th2 < JAXLIE_EPS;
    double th2s = small ? 1.0 : th2, th = sqrt(th2s);
    double c = small ? 1.0 / 12.0 : (1.0 - th * cos(th / 2) / (2.0 * sin(th / 2))) / th2s;
    double W[3][3], WW[3][3];
    hat(w, W);
    mul3(W, W, WW);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) out[i][j] = (i == j ? 1.0 : 0.0) - 0.5 * W[i][j] + c * WW[i][j];
}

static void log_se3(const double *T, double *out) {  /* se3.log_params: (V⁻¹ t, ω) */
    double w = T[0], v[3] = {T[1], T[2], T[3]};
    double n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    int small = n2 < JAXLIE_EPS;
    double n = sqrt(small ? 1.0 : n2), ws = small ? w : 1.0, factor;
    if (small)
        factor = 2.0 / ws - 2.0 / 3.0 * n2 / (ws * ws * ws);
    else if (fabs(w) < JAXLIE_EPS)
        factor = (w > 0 ? 1.0 : -1.0) * M_PI / n;
    else
        factor = 2.0 * atan2(w < 0 ? -n : n, fabs(w)) / n;
    double omega[3] = {factor * v[0], factor * v[1], factor * v[2]}, Vi[3][3];
    so3_left_jacobian_inverse(omega, Vi);
    for (int i = 0; i < 3; ++i) out[i] = Vi[i][0] * T[4] + Vi[i][1] * T[5] + Vi[i][2] * T[6];
    for (int i = 0; i < 3; ++i) out[3 + i] = omega[i];
}

/* se3.right_jacobian_inverse: J_r⁻¹(ξ) = [[A, −A Q A], [0, A]], A = J_l⁻¹(−ω), Q = Q(−ρ, −ω)
 * (Barfoot's, its coefficients by their series below θ = Q_SERIES); out (6, 6) row-major. */
static void right_jacobian_inverse(const double *xi, double *out) {
    double rho[3] = {-xi[0], -xi[1], -xi[2]}, phi[3] = {-xi[3], -xi[4], -xi[5]};
    double th2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2];
    int small = th2 < Q_SERIES * Q_SERIES;
    double th = sqrt(small ? 1.0 : th2), s = sin(th), c = cos(th);
    double c1 = small ? 1.0 / 6 - th2 / 120 + th2 * th2 / 5040 : (th - s) / (th * th * th);
    double c2 = small ? 1.0 / 24 - th2 / 720 + th2 * th2 / 40320 : (th * th + 2 * c - 2) / (2 * th * th * th * th);
    double c3 = small ? 1.0 / 120 - th2 / 2520 + th2 * th2 / 120960
                      : (2 * th - 3 * s + th * c) / (2 * th * th * th * th * th);
    double P[3][3], Rh[3][3], PR[3][3], RP[3][3], PP[3][3], PRP[3][3], PPR[3][3], RPP[3][3], PRPP[3][3],
        PPRP[3][3], Q[3][3], A[3][3], AQ[3][3], AQA[3][3];
    hat(phi, P);
    hat(rho, Rh);
    mul3(P, Rh, PR);
    mul3(Rh, P, RP);
    mul3(P, P, PP);
    mul3(PR, P, PRP);
    mul3(PP, Rh, PPR);
    mul3(RP, P, RPP);
    mul3(PRP, P, PRPP);
    mul3(PP, RP, PPRP);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            Q[i][j] = 0.5 * Rh[i][j] + c1 * (PR[i][j] + RP[i][j] + PRP[i][j])
                      + c2 * (PPR[i][j] + RPP[i][j] - 3 * PRP[i][j]) + c3 * (PRPP[i][j] + PPRP[i][j]);
    so3_left_jacobian_inverse(phi, A);
    mul3(A, Q, AQ);
    mul3(AQ, A, AQA);
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j < 6; ++j) out[6 * i + j] = 0.0;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            out[6 * i + j] = A[i][j];
            out[6 * (3 + i) + 3 + j] = A[i][j];
            out[6 * i + 3 + j] = -AQA[i][j];
        }
}

/* Ad(T) (6, 6) in (v, ω) order: [[R, [t]× R], [0, R]] */
static void adjoint(const double *T, double out[6][6]) {
    double R[3][3], tx[3][3], tR[3][3];
    rotation(T, R);
    hat(T + 4, tx);
    mul3(tx, R, tR);
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j < 6; ++j) out[i][j] = 0.0;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            out[i][j] = R[i][j];
            out[3 + i][3 + j] = R[i][j];
            out[i][3 + j] = tR[i][j];
        }
}

/* The pose prior r = Log(T̄⁻¹ T) and J = J_r⁻¹(r) (n, 6, 6) (factors' pose_prior_linearization);
 * J NULL: r only. */
void pose_prior(int64_t n, const double *T, const double *prior, double *r, double *J) {
    for (int64_t k = 0; k < n; ++k) {
        double inv[7], E[7];
        inverse(prior + 7 * k, inv);
        compose(inv, T + 7 * k, E);
        log_se3(E, r + 6 * k);
        if (J) right_jacobian_inverse(r + 6 * k, J + 36 * k);
    }
}

/* The pose between r = Log(T̄₁₂⁻¹ D), D = T₁⁻¹ T₂, and J = [−J_r⁻¹(r) Ad(D⁻¹), J_r⁻¹(r)]
 * (n, 6, 12) (factors' pose_between_linearization); J NULL: r only. */
void pose_between(int64_t n, const double *T1, const double *T2, const double *T12, double *r, double *J) {
    for (int64_t k = 0; k < n; ++k) {
        double inv1[7], D[7], inv12[7], E[7];
        inverse(T1 + 7 * k, inv1);
        compose(inv1, T2 + 7 * k, D);
        inverse(T12 + 7 * k, inv12);
        compose(inv12, D, E);
        double *rk = r + 6 * k;
        log_se3(E, rk);
        if (!J) continue;
        double Jr[36], Dinv[7], Ad[6][6];
        right_jacobian_inverse(rk, Jr);
        inverse(D, Dinv);
        adjoint(Dinv, Ad);
        double *Jk = J + 72 * k;
        for (int i = 0; i < 6; ++i)
            for (int j = 0; j < 6; ++j) {
                double acc = 0.0;
                for (int l = 0; l < 6; ++l) acc += Jr[6 * i + l] * Ad[l][j];
                Jk[12 * i + j] = -acc;
                Jk[12 * i + 6 + j] = Jr[6 * i + j];
            }
    }
}

/* Whitened terms: r̃ = W r (n, m), J̃ = W J (n, m, D) (W (n, m, m), or NULL: r̃ = r, J̃ = J),
 * finite[k] whether r̃[k] and J̃[k] (when given) are all finite, s[k] = ‖r̃[k]‖². In place
 * is not allowed (r_out, J_out are other arrays). */
void whiten(int64_t n, int64_t m, int64_t D, const double *W, const double *r, const double *J, double *r_out,
            double *J_out, uint8_t *finite, double *s) {
    for (int64_t k = 0; k < n; ++k) {
        const double *Wk = W ? W + k * m * m : NULL, *rk = r + k * m, *Jk = J ? J + k * m * D : NULL;
        double *ro = r_out + k * m, *Jo = J_out ? J_out + k * m * D : NULL, ss = 0.0;
        int ok = 1;
        for (int64_t i = 0; i < m; ++i) {
            double acc = 0.0;
            if (Wk)
                for (int64_t a = 0; a < m; ++a) acc += Wk[i * m + a] * rk[a];
            else
                acc = rk[i];
            ro[i] = acc;
            ss += acc * acc;
            ok &= isfinite(acc) != 0;
            if (!Jo) continue;
            for (int64_t j = 0; j < D; ++j) {
                double v = 0.0;
                if (Wk)
                    for (int64_t a = 0; a < m; ++a) v += Wk[i * m + a] * Jk[a * D + j];
                else
                    v = Jk[i * D + j];
                Jo[i * D + j] = v;
                ok &= isfinite(v) != 0;
            }
        }
        finite[k] = (uint8_t)ok;
        s[k] = ss;
    }
}

/* H (n, D(D+1)/2): the upper triangle of each J[k]ᵀ J[k], row-major (i ≤ j); g (n, D) =
 * J[k]ᵀ r[k]; J (n, m, D), r (n, m). */
void gram_upper(int64_t n, int64_t m, int64_t D, const double *J, const double *r, double *H, double *g) {
    const int64_t T = D * (D + 1) / 2;
    for (int64_t k = 0; k < n; ++k) {
        const double *Jk = J + k * m * D, *rk = r + k * m;
        double *Hk = H + k * T, *gk = g + k * D;
        int64_t s = 0;
        for (int64_t i = 0; i < D; ++i) {
            for (int64_t j = i; j < D; ++j) {
                double acc = 0.0;
                for (int64_t a = 0; a < m; ++a) acc += Jk[a * D + i] * Jk[a * D + j];
                Hk[s++] = acc;
            }
            double acc = 0.0;
            for (int64_t a = 0; a < m; ++a) acc += Jk[a * D + i] * rk[a];
            gk[i] = acc;
        }
    }
}

/* gram_upper and scatter_add in one pass, without the per-factor JᵀJ: each J[k]ᵀJ[k] upper
 * entry s added into h[hslots[k T + s]], each (J[k]ᵀr[k])_i into g[gslots[k D + i]]. */
void gram_scatter(int64_t n, int64_t m, int64_t D, const double *J, const double *r, const int64_t *hslots,
                  const int64_t *gslots, double *h, double *g) {
    const int64_t T = D * (D + 1) / 2;
    for (int64_t k = 0; k < n; ++k) {
        const double *Jk = J + k * m * D, *rk = r + k * m;
        const int64_t *hs = hslots + k * T, *gs = gslots + k * D;
        int64_t s = 0;
        for (int64_t i = 0; i < D; ++i) {
            for (int64_t j = i; j < D; ++j) {
                double acc = 0.0;
                for (int64_t a = 0; a < m; ++a) acc += Jk[a * D + i] * Jk[a * D + j];
                h[hs[s++]] += acc;
            }
            double acc = 0.0;
            for (int64_t a = 0; a < m; ++a) acc += Jk[a * D + i] * rk[a];
            g[gs[i]] += acc;
        }
    }
}

/* out[slots[i]] += values[i] for i < n (the per-factor JᵀJ summed into H's slots). */
void scatter_add(int64_t n, const int64_t *slots, const double *values, double *out) {
    for (int64_t i = 0; i < n; ++i) out[slots[i]] += values[i];
}

/* The k-th smallest of x[0..n) (0 ≤ k < n), x reordered so that x[k] holds it, everything
 * before it ≤ it and everything after ≥ it (Hoare's selection, median-of-three pivots). */
static double select_kth(double *x, int64_t n, int64_t k) {
    int64_t lo = 0, hi = n - 1;
    while (hi > lo) {
        int64_t mid = lo + (hi - lo) / 2;
        /* order x[lo], x[mid], x[hi]; the median of the three is the pivot */
        if (x[mid] < x[lo]) { double t = x[mid]; x[mid] = x[lo]; x[lo] = t; }
        if (x[hi] < x[lo]) { double t = x[hi]; x[hi] = x[lo]; x[lo] = t; }
        if (x[hi] < x[mid]) { double t = x[hi]; x[hi] = x[mid]; x[mid] = t; }
        double pivot = x[mid];
        int64_t i = lo, j = hi;
        while (i <= j) {
            while (x[i] < pivot) ++i;
            while (pivot < x[j]) --j;
            if (i <= j) {
                double t = x[i]; x[i] = x[j]; x[j] = t;
                ++i, --j;
            }
        }
        if (k <= j) hi = j;
        else if (k >= i) lo = i;
        else return x[k];
    }
    return x[k];
}

/* The median of each of the k consecutive segments of the finite values v (sizes counts):
 * the middle order statistic, or (x + y)/2 of the two middle ones (np.median's), 0 for an
 * empty segment. buf: scratch of at least the largest count. */
void segment_medians(int64_t k, const double *v, const int64_t *counts, double *buf, double *med) {
    int64_t start = 0;
    for (int64_t s = 0; s < k; ++s) {
        int64_t c = counts[s];
        if (c <= 0) {
            med[s] = 0.0;
            continue;
        }
        for (int64_t i = 0; i < c; ++i) buf[i] = v[start + i];
        int64_t hi = c / 2;  /* the upper middle; the lower is hi − 1 when c is even */
        double x_hi = select_kth(buf, c, hi);
        if (c % 2) {
            med[s] = x_hi;
        } else {
            double x_lo = buf[0];  /* the largest of those before hi */
            for (int64_t i = 1; i < hi; ++i)
                if (buf[i] > x_lo) x_lo = buf[i];
            med[s] = (x_lo + x_hi) / 2.0;
        }
        start += c;
    }
}

/* An importable, empty module: the functions above are reached through ctypes. */
static struct PyModuleDef kernels_module = {PyModuleDef_HEAD_INIT, "_kernels",
                                            "spdslam's compiled kernels (loaded with ctypes).", -1, NULL};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&kernels_module); }
