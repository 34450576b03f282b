/* FMI 2.0 Model Exchange + Co-Simulation of a linear state-space model
 *
 *     x' = A x + B u,    y = C x + D u          (SI units, A (NX x NX), B (NX x NU), ...)
 *
 * written by pipeline.apps.exports.fmu (fe-reduced-body). The model data (matrices in
 * row-major order, names, value references) is in model_data.h, generated per FMU; this
 * file is the same for every FMU. Build (any C99 compiler, the FMI 2.0 headers on the
 * include path, e.g. the c-code folder of fmpy or of the FMI standard):
 *
 *     cc -std=c99 -O2 -shared -fPIC -I<fmi2 headers> -o <modelIdentifier>.so fmu.c -lm
 *
 * Value references: 0..NX-1 states x, NX..2NX-1 their derivatives, then NU inputs u, NY
 * outputs y and NP damping-ratio parameters (one per mode k: A[v_k][v_k] = -2 zeta_k w_k,
 * and the acceleration rows of C, D follow as C_acc = C_vel A, D_acc = C_vel B).
 *
 * Co-Simulation: fmi2DoStep(h) advances x exactly for an input held constant over the
 * step (zero-order hold): [[Phi, Gamma], [0, I]] = expm([[A, B], [0, 0]] h), computed here
 * by balancing (power-of-two diagonal scaling: exact), scaling and squaring and the (6,6)
 * Pade approximant (Golub & Van Loan, Matrix Computations, alg. 11.3.1; relative error of
 * the approximant <= 3.4e-16 with ||M/2^s|| <= 1/2). Phi, Gamma are recomputed when h or a
 * parameter changes. Model Exchange: the importer's integrator calls fmi2GetDerivatives.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>
#include "fmi2Functions.h"
#include "model_data.h"

#define NA (NX + NU) /* size of the augmented matrix */
#define VR_X 0
#define VR_DX (NX)
#define VR_U (2 * NX)
#define VR_Y (2 * NX + NU)
#define VR_P (2 * NX + NU + NY)
#define VR_END (2 * NX + NU + NY + NP)

typedef struct {
    double x[NX > 0 ? NX : 1], u[NU > 0 ? NU : 1];
    double A[NX * NX > 0 ? NX * NX : 1], C[NY * NX > 0 ? NY * NX : 1];
    double D[NY * NU > 0 ? NY * NU : 1];
    double zeta[NP > 0 ? NP : 1];
    double Phi[NX * NX > 0 ? NX * NX : 1], Gam[NX * NU > 0 ? NX * NU : 1];
    double h_cached; /* step of Phi, Gam; <= 0: none */
    double time;
    int dirty; /* A, C, D must follow zeta */
    fmi2Type type;
    fmi2CallbackFunctions cb;
    char *name;
} Model;

static void log_error(Model *m, const char *msg) {
    if (m && m->cb.logger)
        m->cb.logger(m->cb.componentEnvironment, m->name, fmi2Error, "logStatusError", "%s", msg);
}

/* A, C, D from the stored matrices and the damping parameters */
static void update_matrices(Model *m) {
    int i, j, k, r;
    memcpy(m->A, A0, sizeof(double) * NX * NX);
    memcpy(m->C, C0, sizeof(double) * NY * NX);
    memcpy(m->D, D0, sizeof(double) * NY * NU);
    for (k = 0; k < NP; k++)
        m->A[MODE_VEL[k] * NX + MODE_VEL[k]] = -2.0 * m->zeta[k] * OMEGA[k];
    if (NP > 0) {
        for (r = 0; r < NACC; r++) { /* C_acc = C_vel A, D_acc = C_vel B */
            const int ia = ACC_ROW[r], iv = VEL_ROW[r];
            for (j = 0; j < NX; j++) {
                double s = 0.0;
                for (i = 0; i < NX; i++) s += C0[iv * NX + i] * m->A[i * NX + j];
                m->C[ia * NX + j] = s;
            }
            for (j = 0; j < NU; j++) {
                double s = 0.0; /* D_vel = 0 (checked at export) */
                for (i = 0; i < NX; i++) s += C0[iv * NX + i] * B0[i * NU + j];
                m->D[ia * NU + j] = s;
            }
        }
    }
    m->dirty = 0;
    m->h_cached = -1.0;
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
static int discretise(Model *m, double h) {
    double *M = (double *)calloc(8 * NA * NA + NA, sizeof(double));
    double *E = M + NA * NA, *work = M + 2 * NA * NA;
    int i, j, rc;
    if (!M) return -1;
    for (i = 0; i < NX; i++) {
        for (j = 0; j < NX; j++) M[i * NA + j] = m->A[i * NX + j] * h;
        for (j = 0; j < NU; j++) M[i * NA + NX + j] = B0[i * NU + j] * h;
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

static double derivative(const Model *m, int i) {
    double s = 0.0;
    int j;
    for (j = 0; j < NX; j++) s += m->A[i * NX + j] * m->x[j];
    for (j = 0; j < NU; j++) s += B0[i * NU + j] * m->u[j];
    return s;
}

static double output(const Model *m, int i) {
    double s = 0.0;
    int j;
    for (j = 0; j < NX; j++) s += m->C[i * NX + j] * m->x[j];
    for (j = 0; j < NU; j++) s += m->D[i * NU + j] * m->u[j];
    return s;
}

/* ---------------------------------------------------------------- FMI 2.0 functions */
const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cat[]) {
    (void)c; (void)on; (void)n; (void)cat;
    return fmi2OK;
}

static void reset_model(Model *m) {
    int k;
    memset(m->x, 0, sizeof(m->x));
    memset(m->u, 0, sizeof(m->u));
    for (k = 0; k < NP; k++) m->zeta[k] = ZETA0[k];
    for (k = 0; k < NX; k++) m->x[k] = X0[k];
    m->time = 0.0;
    update_matrices(m);
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid,
                              fmi2String location, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean logging) {
    Model *m;
    (void)location; (void)visible; (void)logging;
    if (!guid || strcmp(guid, MODEL_GUID) != 0) {
        if (functions && functions->logger)
            functions->logger(functions->componentEnvironment, name, fmi2Error, "logStatusError",
                              "fmi2Instantiate: GUID %s does not match %s", guid ? guid : "(null)",
                              MODEL_GUID);
        return NULL;
    }
    m = (Model *)calloc(1, sizeof(Model));
    if (!m) return NULL;
    if (functions) m->cb = *functions;
    m->name = (char *)malloc(strlen(name ? name : "") + 1);
    if (m->name) strcpy(m->name, name ? name : "");
    m->type = type;
    reset_model(m);
    return m;
}

void fmi2FreeInstance(fmi2Component c) {
    Model *m = (Model *)c;
    if (!m) return;
    free(m->name);
    free(m);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDefined, fmi2Real tol,
                               fmi2Real start, fmi2Boolean stopDefined, fmi2Real stop) {
    (void)tolDefined; (void)tol; (void)stopDefined; (void)stop;
    ((Model *)c)->time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Model *m = (Model *)c;
    if (m->dirty) update_matrices(m);
    return fmi2OK;
}
fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2Reset(fmi2Component c) { reset_model((Model *)c); return fmi2OK; }

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real v[]) {
    Model *m = (Model *)c;
    size_t i;
    if (m->dirty) update_matrices(m);
    for (i = 0; i < n; i++) {
        const fmi2ValueReference r = vr[i];
        if (r < VR_DX) v[i] = m->x[r - VR_X];
        else if (r < VR_U) v[i] = derivative(m, (int)(r - VR_DX));
        else if (r < VR_Y) v[i] = m->u[r - VR_U];
        else if (r < VR_P) v[i] = output(m, (int)(r - VR_Y));
        else if (r < VR_END) v[i] = m->zeta[r - VR_P];
        else { log_error(m, "fmi2GetReal: unknown value reference"); return fmi2Error; }
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                       const fmi2Real v[]) {
    Model *m = (Model *)c;
    size_t i;
    for (i = 0; i < n; i++) {
        const fmi2ValueReference r = vr[i];
        if (r < VR_DX) m->x[r] = v[i];
        else if (r >= VR_U && r < VR_Y) m->u[r - VR_U] = v[i];
        else if (r >= VR_P && r < VR_END) {
            if (!(v[i] >= 0.0)) { log_error(m, "fmi2SetReal: a damping ratio must be >= 0"); return fmi2Error; }
            m->zeta[r - VR_P] = v[i];
            m->dirty = 1;
        } else { log_error(m, "fmi2SetReal: value reference is not settable"); return fmi2Error; }
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[]) {
    (void)vr; (void)v; if (n) { log_error((Model *)c, "no Integer variables"); return fmi2Error; } return fmi2OK;
}
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[]) {
    (void)vr; (void)v; if (n) { log_error((Model *)c, "no Boolean variables"); return fmi2Error; } return fmi2OK;
}
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[]) {
    (void)vr; (void)v; if (n) { log_error((Model *)c, "no String variables"); return fmi2Error; } return fmi2OK;
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer v[]) {
    (void)vr; (void)v; if (n) { log_error((Model *)c, "no Integer variables"); return fmi2Error; } return fmi2OK;
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean v[]) {
    (void)vr; (void)v; if (n) { log_error((Model *)c, "no Boolean variables"); return fmi2Error; } return fmi2OK;
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[]) {
    (void)vr; (void)v; if (n) { log_error((Model *)c, "no String variables"); return fmi2Error; } return fmi2OK;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)s; log_error((Model *)c, "FMU state not supported"); return fmi2Error; }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { (void)s; log_error((Model *)c, "FMU state not supported"); return fmi2Error; }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)s; log_error((Model *)c, "FMU state not supported"); return fmi2Error; }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) { (void)s; (void)n; log_error((Model *)c, "FMU state not supported"); return fmi2Error; }
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n) { (void)s; (void)b; (void)n; log_error((Model *)c, "FMU state not supported"); return fmi2Error; }
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *s) { (void)s; (void)b; (void)n; log_error((Model *)c, "FMU state not supported"); return fmi2Error; }
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz,
                                        const fmi2Real du[], fmi2Real dz[]) {
    (void)u; (void)nu; (void)z; (void)nz; (void)du; (void)dz;
    log_error((Model *)c, "directional derivatives not provided");
    return fmi2Error;
}

/* Model Exchange */
fmi2Status fmi2EnterEventMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *e) {
    (void)c;
    e->newDiscreteStatesNeeded = fmi2False;
    e->terminateSimulation = fmi2False;
    e->nominalsOfContinuousStatesChanged = fmi2False;
    e->valuesOfContinuousStatesChanged = fmi2False;
    e->nextEventTimeDefined = fmi2False;
    e->nextEventTime = 0.0;
    return fmi2OK;
}
fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSet, fmi2Boolean *enter,
                                       fmi2Boolean *terminate) {
    (void)c; (void)noSet;
    *enter = fmi2False;
    *terminate = fmi2False;
    return fmi2OK;
}
fmi2Status fmi2SetTime(fmi2Component c, fmi2Real t) { ((Model *)c)->time = t; return fmi2OK; }
fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t n) {
    Model *m = (Model *)c;
    if (n != NX) { log_error(m, "fmi2SetContinuousStates: wrong number of states"); return fmi2Error; }
    memcpy(m->x, x, sizeof(double) * NX);
    return fmi2OK;
}
fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t n) {
    Model *m = (Model *)c;
    size_t i;
    if (n != NX) { log_error(m, "fmi2GetDerivatives: wrong number of states"); return fmi2Error; }
    if (m->dirty) update_matrices(m);
    for (i = 0; i < n; i++) dx[i] = derivative(m, (int)i);
    return fmi2OK;
}
fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t n) {
    (void)z;
    if (n != 0) { log_error((Model *)c, "no event indicators"); return fmi2Error; }
    return fmi2OK;
}
fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t n) {
    Model *m = (Model *)c;
    if (n != NX) { log_error(m, "fmi2GetContinuousStates: wrong number of states"); return fmi2Error; }
    memcpy(x, m->x, sizeof(double) * NX);
    return fmi2OK;
}
fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x[], size_t n) {
    size_t i;
    if (n != NX) { log_error((Model *)c, "wrong number of states"); return fmi2Error; }
    for (i = 0; i < n; i++) x[i] = NOMINAL[i];
    return fmi2OK;
}

/* Co-Simulation */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                       const fmi2Integer order[], const fmi2Real v[]) {
    (void)vr; (void)order; (void)v;
    if (n) { log_error((Model *)c, "input derivatives not supported (canInterpolateInputs=false)"); return fmi2Error; }
    return fmi2OK;
}
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                        const fmi2Integer order[], fmi2Real v[]) {
    (void)vr; (void)order; (void)v;
    if (n) { log_error((Model *)c, "output derivatives not supported"); return fmi2Error; }
    return fmi2OK;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior) {
    Model *m = (Model *)c;
    double xn[NX > 0 ? NX : 1];
    int i, j;
    (void)noSetPrior;
    if (!(h > 0.0)) {
        if (h == 0.0) return fmi2OK;
        log_error(m, "fmi2DoStep: negative step size");
        return fmi2Error;
    }
    if (m->dirty) update_matrices(m);
    if (h != m->h_cached && discretise(m, h) != 0) {
        log_error(m, "fmi2DoStep: matrix exponential failed (non-finite model or step)");
        return fmi2Error;
    }
    for (i = 0; i < NX; i++) {
        double s = 0.0;
        for (j = 0; j < NX; j++) s += m->Phi[i * NX + j] * m->x[j];
        for (j = 0; j < NU; j++) s += m->Gam[i * NU + j] * m->u[j];
        xn[i] = s;
    }
    memcpy(m->x, xn, sizeof(double) * NX);
    m->time = t + h;
    return fmi2OK;
}
fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }
fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v) {
    (void)c; (void)s; *v = fmi2OK; return fmi2OK;
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    if (s == fmi2LastSuccessfulTime) { *v = ((Model *)c)->time; return fmi2OK; }
    return fmi2Discard;
}
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *v) {
    (void)c; (void)s; (void)v; return fmi2Discard;
}
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *v) {
    (void)c; if (s == fmi2Terminated) { *v = fmi2False; return fmi2OK; } return fmi2Discard;
}
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *v) {
    (void)c; (void)s; (void)v; return fmi2Discard;
}
