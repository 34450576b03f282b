/* Linear state-space model of an FMU written by pipeline.apps.exports.fmu (fe-reduced-body):
 *
 *     x' = A x + B u,    y = C x + D u          (SI units)
 *
 * This part is the same for FMI 2.0 and FMI 3.0; the FMI functions follow it in the same
 * fmu.c (fmi2_api.c or fmi3_api.c of the exporter). The model data (matrices in row-major
 * order, 17 significant digits) is in model_data.h, generated per FMU.
 *
 * Parameters par[0..NZ-1]: damping ratios zeta_k of the modes; par[NZ] (when NF > 0): the
 * output filter's cut-off f_c in Hz. The model is rebuilt from them (update_matrices):
 *
 *   plant (NXP states, NYP outputs), affine in zeta (checked at export):
 *     A_p = A_BASE + sum_k zeta_k GA[:, k] e_{VCOL_k}^T,   B_p = B_P
 *     C_p = C_BASE + sum_k zeta_k GC[:, k] e_{VCOL_k}^T,   D_p = D_P
 *   (a modal model: A[v_k, v_k] = -2 zeta_k omega_k in the velocity column v_k; outputs
 *   built from A, like acceleration = C_vel A, follow in GC);
 *   output filter (NF > 0) in series, K = 2 pi f_c, fed by the plant outputs FIN_ROW:
 *     A = [[A_p, 0], [K BF1 C_p[FIN], K AF1]],  B = [[B_p], [K BF1 D_p[FIN]]],
 *     C = [0, CF1 K^CF_POW],  D = 0
 *   (AF1, BF1, CF1: the filter at K = 1; row r of C scales with K^CF_POW[r]).
 *
 * Co-Simulation advances x exactly for an input held constant over the step (zero-order
 * hold): [[Phi, Gamma], [0, I]] = expm([[A, B], [0, 0]] h), computed here by balancing
 * (power-of-two diagonal scaling: exact), scaling and squaring and the (6,6) Pade
 * approximant (Golub & Van Loan, Matrix Computations, alg. 11.3.1; relative error of the
 * approximant <= 3.4e-16 with ||M/2^s|| <= 1/2). Phi, Gamma are recomputed when h or a
 * parameter changes. Model Exchange hands A x + B u to the importer's integrator.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>
#include "model_data.h"

#define DIM(n) ((n) > 0 ? (n) : 1)
#define NA (NX + NU) /* size of the augmented matrix */
#define NPAR (NZ + (NF > 0 ? 1 : 0))
#define PI_2 6.283185307179586

typedef struct {
    double x[DIM(NX)], u[DIM(NU)], par[DIM(NPAR)];
    double A[DIM(NX * NX)], B[DIM(NX * NU)], C[DIM(NY * NX)], D[DIM(NY * NU)];
    double Cp[DIM(NYP * NXP)]; /* the plant's C (its D is D_P) */
    double Phi[DIM(NX * NX)], Gam[DIM(NX * NU)];
    double h_cached; /* step of Phi, Gam; <= 0: none */
    double time;
    int dirty; /* A, B, C, D must follow par */
} Core;

/* A, B, C, D from the stored matrices and the parameters */
static void update_matrices(Core *m) {
    int i, j, k, l;
    memset(m->A, 0, sizeof(m->A));
    memset(m->B, 0, sizeof(m->B));
    memset(m->C, 0, sizeof(m->C));
    memset(m->D, 0, sizeof(m->D));
    for (i = 0; i < NXP; i++) {
        for (j = 0; j < NXP; j++) m->A[i * NX + j] = A_BASE[i * NXP + j];
        for (j = 0; j < NU; j++) m->B[i * NU + j] = B_P[i * NU + j];
    }
    for (i = 0; i < NYP * NXP; i++) m->Cp[i] = C_BASE[i];
    for (k = 0; k < NZ; k++) {
        for (i = 0; i < NXP; i++) m->A[i * NX + VCOL[k]] += m->par[k] * GA[i * DIM(NZ) + k];
        for (i = 0; i < NYP; i++) m->Cp[i * NXP + VCOL[k]] += m->par[k] * GC[i * DIM(NZ) + k];
    }
    if (NF == 0) {
        for (i = 0; i < NY * NX; i++) m->C[i] = m->Cp[i];
        for (i = 0; i < NY * NU; i++) m->D[i] = D_P[i];
    } else {
        const double K = PI_2 * m->par[NZ];
        for (i = 0; i < NF; i++) {
            for (j = 0; j < NXP; j++) {
                double s = 0.0;
                for (l = 0; l < NFIN; l++) s += BF1[i * DIM(NFIN) + l] * m->Cp[FIN_ROW[l] * NXP + j];
                m->A[(NXP + i) * NX + j] = K * s;
            }
            for (j = 0; j < NF; j++) m->A[(NXP + i) * NX + NXP + j] = K * AF1[i * DIM(NF) + j];
            for (j = 0; j < NU; j++) {
                double s = 0.0;
                for (l = 0; l < NFIN; l++) s += BF1[i * DIM(NFIN) + l] * D_P[FIN_ROW[l] * NU + j];
                m->B[(NXP + i) * NU + j] = K * s;
            }
        }
        for (i = 0; i < NY; i++)
            for (j = 0; j < NF; j++)
                m->C[i * NX + NXP + j] = CF1[i * DIM(NF) + j] * pow(K, CF_POW[i]);
    }
    m->dirty = 0;
    m->h_cached = -1.0;
}

/* parameter k := v; NULL, or why v is refused */
static const char *set_parameter(Core *m, int k, double v) {
    if (k < NZ && !(v >= 0.0 && v < INFINITY)) return "a damping ratio must be finite and >= 0";
    if (k >= NZ && !(v > 0.0 && v < INFINITY)) return "the filter cut-off must be finite and > 0 Hz";
    m->par[k] = v;
    m->dirty = 1;
    return NULL;
}

static void reset_core(Core *m) {
    int k;
    memset(m->u, 0, sizeof(m->u));
    for (k = 0; k < NX; k++) m->x[k] = X0[k];
    for (k = 0; k < NPAR; k++) m->par[k] = PAR0[k];
    m->time = 0.0;
    update_matrices(m);
}

/* ---------------------------------------------------------------- matrix exponential */
static void matmul(int n, const double *X, const double *Y, double *Z) {
    int i, j, k;
    for (i = 0; i < n; i++)
        for (j = 0; j < n; j++) {
            double s = 0.0;
            for (k = 0; k < n; k++) s += X[i * n + k] * Y[k * n + j];
            Z[i * n + j] = s;
        }
}

/* solve Q X = P in place (X -> P) by LU with partial pivoting; 0 on success */
static int solve(int n, double *Q, double *P) {
    int i, j, k, c;
    for (k = 0; k < n; k++) {
        int piv = k;
        double best = fabs(Q[k * n + k]);
        for (i = k + 1; i < n; i++)
            if (fabs(Q[i * n + k]) > best) { best = fabs(Q[i * n + k]); piv = i; }
        if (best == 0.0) return -1;
        if (piv != k) {
            for (j = 0; j < n; j++) {
                double t = Q[k * n + j]; Q[k * n + j] = Q[piv * n + j]; Q[piv * n + j] = t;
                t = P[k * n + j]; P[k * n + j] = P[piv * n + j]; P[piv * n + j] = t;
            }
        }
        for (i = k + 1; i < n; i++) {
            const double f = Q[i * n + k] / Q[k * n + k];
            if (f == 0.0) continue;
            for (j = k; j < n; j++) Q[i * n + j] -= f * Q[k * n + j];
            for (c = 0; c < n; c++) P[i * n + c] -= f * P[k * n + c];
        }
    }
    for (k = n - 1; k >= 0; k--)
        for (c = 0; c < n; c++) {
            double s = P[k * n + c];
            for (j = k + 1; j < n; j++) s -= Q[k * n + j] * P[j * n + c];
            P[k * n + c] = s / Q[k * n + k];
        }
    return 0;
}

/* E = expm(M), M (n x n) overwritten; work: 5 n^2 doubles. 0 on success */
static int expm(int n, double *M, double *E, double *work) {
    double *X = work, *N = work + n * n, *Dn = work + 2 * n * n, *T = work + 3 * n * n;
    double *scale = work + 4 * n * n;
    static const double c[7] = {1.0, 0.5, 5.0 / 44.0, 1.0 / 66.0, 1.0 / 792.0,
                                1.0 / 15840.0, 1.0 / 665280.0};
    int i, j, k, s = 0, it, changed;
    double norm = 0.0;
    /* balance: D^-1 M D with D = powers of two (exact), rows and columns of like norm */
    for (i = 0; i < n; i++) scale[i] = 1.0;
    for (it = 0, changed = 1; changed && it < 64; it++) {
        changed = 0;
        for (i = 0; i < n; i++) {
            double rn = 0.0, cn = 0.0, f = 1.0;
            for (j = 0; j < n; j++)
                if (j != i) { cn += fabs(M[j * n + i]); rn += fabs(M[i * n + j]); }
            if (cn == 0.0 || rn == 0.0) continue;
            while (cn < rn / 2.0) { cn *= 2.0; rn /= 2.0; f *= 2.0; }
            while (cn >= rn * 2.0) { cn /= 2.0; rn *= 2.0; f /= 2.0; }
            if (f != 1.0) {
                changed = 1;
                scale[i] *= f;
                for (j = 0; j < n; j++) { M[i * n + j] /= f; M[j * n + i] *= f; }
            }
        }
    }
    for (i = 0; i < n; i++) {
        double r = 0.0;
        for (j = 0; j < n; j++) r += fabs(M[i * n + j]);
        if (r > norm) norm = r;
    }
    if (!(norm < INFINITY)) return -1;
    while (norm > 0.5) { norm /= 2.0; s++; }
    for (i = 0; i < n * n; i++) M[i] = ldexp(M[i], -s);
    /* N = sum c_k M^k, Dn = sum (-1)^k c_k M^k */
    memcpy(X, M, sizeof(double) * n * n);
    for (i = 0; i < n * n; i++) { N[i] = c[1] * M[i]; Dn[i] = -c[1] * M[i]; }
    for (i = 0; i < n; i++) { N[i * n + i] += 1.0; Dn[i * n + i] += 1.0; }
    for (k = 2; k <= 6; k++) {
        matmul(n, M, X, T);
        memcpy(X, T, sizeof(double) * n * n);
        for (i = 0; i < n * n; i++) {
            N[i] += c[k] * X[i];
            Dn[i] += ((k % 2) ? -c[k] : c[k]) * X[i];
        }
    }
    if (solve(n, Dn, N) != 0) return -1; /* N = Dn^-1 N */
    for (k = 0; k < s; k++) {
        matmul(n, N, N, T);
        memcpy(N, T, sizeof(double) * n * n);
    }
    for (i = 0; i < n; i++) /* undo the balancing: E = D N D^-1 */
        for (j = 0; j < n; j++) E[i * n + j] = N[i * n + j] * scale[i] / scale[j];
    return 0;
}

/* Phi, Gamma of the step h (zero-order hold) */
static int discretise(Core *m, double h) {
    double *M = (double *)calloc(8 * NA * NA + NA, sizeof(double));
    double *E = M + NA * NA, *work = M + 2 * NA * NA;
    int i, j, rc;
    if (!M) return -1;
    for (i = 0; i < NX; i++) {
        for (j = 0; j < NX; j++) M[i * NA + j] = m->A[i * NX + j] * h;
        for (j = 0; j < NU; j++) M[i * NA + NX + j] = m->B[i * NU + j] * h;
    }
    rc = expm(NA, M, E, work);
    if (rc == 0) {
        for (i = 0; i < NX; i++) {
            for (j = 0; j < NX; j++) m->Phi[i * NX + j] = E[i * NA + j];
            for (j = 0; j < NU; j++) m->Gam[i * NU + j] = E[i * NA + NX + j];
        }
        m->h_cached = h;
    }
    free(M);
    return rc;
}

/* x(t + h) = Phi x + Gamma u; NULL, or what failed */
static const char *core_step(Core *m, double h) {
    double xn[DIM(NX)];
    int i, j;
    if (h == 0.0) return NULL;
    if (!(h > 0.0)) return "negative step size";
    if (m->dirty) update_matrices(m);
    if (h != m->h_cached && discretise(m, h) != 0)
        return "matrix exponential failed (non-finite model or step)";
    for (i = 0; i < NX; i++) {
        double s = 0.0;
        for (j = 0; j < NX; j++) s += m->Phi[i * NX + j] * m->x[j];
        for (j = 0; j < NU; j++) s += m->Gam[i * NU + j] * m->u[j];
        xn[i] = s;
    }
    memcpy(m->x, xn, sizeof(double) * NX);
    m->time += h;
    return NULL;
}

static double derivative(Core *m, int i) {
    double s = 0.0;
    int j;
    if (m->dirty) update_matrices(m);
    for (j = 0; j < NX; j++) s += m->A[i * NX + j] * m->x[j];
    for (j = 0; j < NU; j++) s += m->B[i * NU + j] * m->u[j];
    return s;
}

static double output(Core *m, int i) {
    double s = 0.0;
    int j;
    if (m->dirty) update_matrices(m);
    for (j = 0; j < NX; j++) s += m->C[i * NX + j] * m->x[j];
    for (j = 0; j < NU; j++) s += m->D[i * NU + j] * m->u[j];
    return s;
}

