/* FMI 3.0 Model Exchange + Co-Simulation functions of the model above (fmu_core.c).
 *
 * Build (any C99 compiler, the FMI 3.0 headers on the include path, e.g. the c-code
 * folder of fmpy or of the FMI standard):
 *
 *     cc -std=c99 -O2 -shared -fPIC -I<fmi3 headers> -o <modelIdentifier>.so fmu.c -lm
 *
 * Value references: 0 time, 1 the state vector x (an array of NX), 2 der(x) (NX), then NU
 * inputs, NY outputs and NPAR parameters (damping ratios, then the filter cut-off in Hz).
 * Only Float64 variables; Scheduled Execution, clocks and FMU states are not provided.
 */
#include "fmi3Functions.h"

#define VR_TIME 0
#define VR_X 1
#define VR_DX 2
#define VR_U 3
#define VR_Y (3 + NU)
#define VR_P (3 + NU + NY)
#define VR_END (3 + NU + NY + NPAR)

typedef struct {
    Core c;
    int cosim;
    fmi3InstanceEnvironment env;
    fmi3LogMessageCallback log;
    char *name;
} Model;

static fmi3Status fail(Model *m, const char *msg) {
    if (m && m->log) m->log(m->env, fmi3Error, "logStatusError", msg);
    return fmi3Error;
}

/* the number of values the value reference r carries (0: unknown) */
static size_t n_values(fmi3ValueReference r) {
    if (r == VR_X || r == VR_DX) return NX;
    return r < VR_END ? 1 : 0;
}

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance i, fmi3Boolean on, size_t n, const fmi3String cat[]) {
    (void)i; (void)on; (void)n; (void)cat;
    return fmi3OK;
}

static fmi3Instance instantiate(fmi3String name, fmi3String token, int cosim,
                                fmi3InstanceEnvironment env, fmi3LogMessageCallback log) {
    Model *m;
    if (!token || strcmp(token, MODEL_GUID) != 0) {
        if (log) log(env, fmi3Error, "logStatusError",
                     "fmi3Instantiate: the instantiation token does not match " MODEL_GUID);
        return NULL;
    }
    m = (Model *)calloc(1, sizeof(Model));
    if (!m) return NULL;
    m->cosim = cosim;
    m->env = env;
    m->log = log;
    m->name = (char *)malloc(strlen(name ? name : "") + 1);
    if (m->name) strcpy(m->name, name ? name : "");
    reset_core(&m->c);
    return m;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String name, fmi3String token, fmi3String resources,
                                          fmi3Boolean visible, fmi3Boolean logging,
                                          fmi3InstanceEnvironment env, fmi3LogMessageCallback log) {
    (void)resources; (void)visible; (void)logging;
    return instantiate(name, token, 0, env, log);
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String name, fmi3String token, fmi3String resources,
                                         fmi3Boolean visible, fmi3Boolean logging,
                                         fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference required[], size_t nRequired,
                                         fmi3InstanceEnvironment env, fmi3LogMessageCallback log,
                                         fmi3IntermediateUpdateCallback update) {
    (void)resources; (void)visible; (void)logging; (void)eventModeUsed;
    (void)earlyReturnAllowed; (void)required; (void)nRequired; (void)update;
    return instantiate(name, token, 1, env, log);
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String name, fmi3String token,
                                               fmi3String resources, fmi3Boolean visible,
                                               fmi3Boolean logging, fmi3InstanceEnvironment env,
                                               fmi3LogMessageCallback log,
                                               fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lock,
                                               fmi3UnlockPreemptionCallback unlock) {
    (void)name; (void)token; (void)resources; (void)visible; (void)logging;
    (void)clockUpdate; (void)lock; (void)unlock;
    if (log) log(env, fmi3Error, "logStatusError", "Scheduled Execution is not provided");
    return NULL;
}

void fmi3FreeInstance(fmi3Instance i) {
    Model *m = (Model *)i;
    if (!m) return;
    free(m->name);
    free(m);
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance i, fmi3Boolean tolDefined, fmi3Float64 tol,
                                       fmi3Float64 start, fmi3Boolean stopDefined,
                                       fmi3Float64 stop) {
    (void)tolDefined; (void)tol; (void)stopDefined; (void)stop;
    ((Model *)i)->c.time = start;
    return fmi3OK;
}
fmi3Status fmi3ExitInitializationMode(fmi3Instance i) {
    Model *m = (Model *)i;
    if (m->c.dirty) update_matrices(&m->c);
    return fmi3OK;
}
fmi3Status fmi3EnterEventMode(fmi3Instance i) { (void)i; return fmi3OK; }
fmi3Status fmi3Terminate(fmi3Instance i) { (void)i; return fmi3OK; }
fmi3Status fmi3Reset(fmi3Instance i) { reset_core(&((Model *)i)->c); return fmi3OK; }

fmi3Status fmi3GetFloat64(fmi3Instance i, const fmi3ValueReference vr[], size_t nvr,
                          fmi3Float64 v[], size_t nv) {
    Model *m = (Model *)i;
    size_t k, j, at = 0;
    for (k = 0; k < nvr; k++) {
        const fmi3ValueReference r = vr[k];
        const size_t n = n_values(r);
        if (n == 0) return fail(m, "fmi3GetFloat64: unknown value reference");
        if (at + n > nv) return fail(m, "fmi3GetFloat64: too few values for the value references");
        if (r == VR_TIME) v[at] = m->c.time;
        else if (r == VR_X) for (j = 0; j < NX; j++) v[at + j] = m->c.x[j];
        else if (r == VR_DX) for (j = 0; j < NX; j++) v[at + j] = derivative(&m->c, (int)j);
        else if (r < VR_Y) v[at] = m->c.u[r - VR_U];
        else if (r < VR_P) v[at] = output(&m->c, (int)(r - VR_Y));
        else v[at] = m->c.par[r - VR_P];
        at += n;
    }
    return fmi3OK;
}

fmi3Status fmi3SetFloat64(fmi3Instance i, const fmi3ValueReference vr[], size_t nvr,
                          const fmi3Float64 v[], size_t nv) {
    Model *m = (Model *)i;
    size_t k, j, at = 0;
    for (k = 0; k < nvr; k++) {
        const fmi3ValueReference r = vr[k];
        const size_t n = n_values(r);
        if (n == 0) return fail(m, "fmi3SetFloat64: unknown value reference");
        if (at + n > nv) return fail(m, "fmi3SetFloat64: too few values for the value references");
        if (r == VR_X) for (j = 0; j < NX; j++) m->c.x[j] = v[at + j];
        else if (r >= VR_U && r < VR_Y) m->c.u[r - VR_U] = v[at];
        else if (r >= VR_P) {
            const char *why = set_parameter(&m->c, (int)(r - VR_P), v[at]);
            if (why) return fail(m, why);
        } else return fail(m, "fmi3SetFloat64: value reference is not settable");
        at += n;
    }
    return fmi3OK;
}

/* the model has Float64 variables only: every other type is an error for any reference */
#define NO_GET(T, NAME) \
    fmi3Status fmi3Get##NAME(fmi3Instance i, const fmi3ValueReference vr[], size_t nvr, \
                             T v[], size_t nv) { \
        (void)vr; (void)v; (void)nv; \
        return nvr ? fail((Model *)i, "no " #NAME " variables") : fmi3OK; }
#define NO_SET(T, NAME) \
    fmi3Status fmi3Set##NAME(fmi3Instance i, const fmi3ValueReference vr[], size_t nvr, \
                             const T v[], size_t nv) { \
        (void)vr; (void)v; (void)nv; \
        return nvr ? fail((Model *)i, "no " #NAME " variables") : fmi3OK; }
#define NO_TYPE(T, NAME) NO_GET(T, NAME) NO_SET(T, NAME)
NO_TYPE(fmi3Float32, Float32)
NO_TYPE(fmi3Int8, Int8)
NO_TYPE(fmi3UInt8, UInt8)
NO_TYPE(fmi3Int16, Int16)
NO_TYPE(fmi3UInt16, UInt16)
NO_TYPE(fmi3Int32, Int32)
NO_TYPE(fmi3UInt32, UInt32)
NO_TYPE(fmi3Int64, Int64)
NO_TYPE(fmi3UInt64, UInt64)
NO_TYPE(fmi3Boolean, Boolean)
NO_TYPE(fmi3String, String)

fmi3Status fmi3GetBinary(fmi3Instance i, const fmi3ValueReference vr[], size_t nvr,
                         size_t sizes[], fmi3Binary v[], size_t nv) {
    (void)vr; (void)sizes; (void)v; (void)nv;
    return nvr ? fail((Model *)i, "no Binary variables") : fmi3OK;
}
fmi3Status fmi3SetBinary(fmi3Instance i, const fmi3ValueReference vr[], size_t nvr,
                         const size_t sizes[], const fmi3Binary v[], size_t nv) {
    (void)vr; (void)sizes; (void)v; (void)nv;
    return nvr ? fail((Model *)i, "no Binary variables") : fmi3OK;
}
fmi3Status fmi3GetClock(fmi3Instance i, const fmi3ValueReference vr[], size_t nvr, fmi3Clock v[]) {
    (void)vr; (void)v;
    return nvr ? fail((Model *)i, "no clocks") : fmi3OK;
}
fmi3Status fmi3SetClock(fmi3Instance i, const fmi3ValueReference vr[], size_t nvr,
                        const fmi3Clock v[]) {
    (void)vr; (void)v;
    return nvr ? fail((Model *)i, "no clocks") : fmi3OK;
}

/* dependencies: not provided (the model description lists none, i.e. all) */
fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance i, fmi3ValueReference r, size_t *n) {
    (void)r; (void)n;
    return fail((Model *)i, "variable dependencies are not provided");
}
fmi3Status fmi3GetVariableDependencies(fmi3Instance i, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[],
                                       fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[],
                                       fmi3DependencyKind kinds[], size_t n) {
    (void)dependent; (void)elementIndicesOfDependent; (void)independents;
    (void)elementIndicesOfIndependents; (void)kinds; (void)n;
    return fail((Model *)i, "variable dependencies are not provided");
}

#define NO_STATE(i) fail((Model *)(i), "FMU state not supported")
fmi3Status fmi3GetFMUState(fmi3Instance i, fmi3FMUState *s) { (void)s; return NO_STATE(i); }
fmi3Status fmi3SetFMUState(fmi3Instance i, fmi3FMUState s) { (void)s; return NO_STATE(i); }
fmi3Status fmi3FreeFMUState(fmi3Instance i, fmi3FMUState *s) { (void)s; return NO_STATE(i); }
fmi3Status fmi3SerializedFMUStateSize(fmi3Instance i, fmi3FMUState s, size_t *n) {
    (void)s; (void)n; return NO_STATE(i);
}
fmi3Status fmi3SerializeFMUState(fmi3Instance i, fmi3FMUState s, fmi3Byte b[], size_t n) {
    (void)s; (void)b; (void)n; return NO_STATE(i);
}
fmi3Status fmi3DeserializeFMUState(fmi3Instance i, const fmi3Byte b[], size_t n, fmi3FMUState *s) {
    (void)s; (void)b; (void)n; return NO_STATE(i);
}

#define NO_DERIVATIVES(NAME) \
    fmi3Status fmi3Get##NAME(fmi3Instance i, const fmi3ValueReference unknowns[], size_t nu, \
                             const fmi3ValueReference knowns[], size_t nk, \
                             const fmi3Float64 seed[], size_t ns, fmi3Float64 sens[], \
                             size_t nsens) { \
        (void)unknowns; (void)nu; (void)knowns; (void)nk; (void)seed; (void)ns; (void)sens; \
        (void)nsens; \
        return fail((Model *)i, #NAME " not provided"); }
NO_DERIVATIVES(DirectionalDerivative)
NO_DERIVATIVES(AdjointDerivative)

/* no structural parameters and no clocks */
fmi3Status fmi3EnterConfigurationMode(fmi3Instance i) { return fail((Model *)i, "no structural parameters"); }
fmi3Status fmi3ExitConfigurationMode(fmi3Instance i) { return fail((Model *)i, "no structural parameters"); }
fmi3Status fmi3GetIntervalDecimal(fmi3Instance i, const fmi3ValueReference vr[], size_t n,
                                  fmi3Float64 v[], fmi3IntervalQualifier q[]) {
    (void)vr; (void)n; (void)v; (void)q; return fail((Model *)i, "no clocks");
}
fmi3Status fmi3GetIntervalFraction(fmi3Instance i, const fmi3ValueReference vr[], size_t n,
                                   fmi3UInt64 c[], fmi3UInt64 r[], fmi3IntervalQualifier q[]) {
    (void)vr; (void)n; (void)c; (void)r; (void)q; return fail((Model *)i, "no clocks");
}
fmi3Status fmi3GetShiftDecimal(fmi3Instance i, const fmi3ValueReference vr[], size_t n,
                               fmi3Float64 v[]) {
    (void)vr; (void)n; (void)v; return fail((Model *)i, "no clocks");
}
fmi3Status fmi3GetShiftFraction(fmi3Instance i, const fmi3ValueReference vr[], size_t n,
                                fmi3UInt64 c[], fmi3UInt64 r[]) {
    (void)vr; (void)n; (void)c; (void)r; return fail((Model *)i, "no clocks");
}
fmi3Status fmi3SetIntervalDecimal(fmi3Instance i, const fmi3ValueReference vr[], size_t n,
                                  const fmi3Float64 v[]) {
    (void)vr; (void)n; (void)v; return fail((Model *)i, "no clocks");
}
fmi3Status fmi3SetIntervalFraction(fmi3Instance i, const fmi3ValueReference vr[], size_t n,
                                   const fmi3UInt64 c[], const fmi3UInt64 r[]) {
    (void)vr; (void)n; (void)c; (void)r; return fail((Model *)i, "no clocks");
}
fmi3Status fmi3SetShiftDecimal(fmi3Instance i, const fmi3ValueReference vr[], size_t n,
                               const fmi3Float64 v[]) {
    (void)vr; (void)n; (void)v; return fail((Model *)i, "no clocks");
}
fmi3Status fmi3SetShiftFraction(fmi3Instance i, const fmi3ValueReference vr[], size_t n,
                                const fmi3UInt64 c[], const fmi3UInt64 r[]) {
    (void)vr; (void)n; (void)c; (void)r; return fail((Model *)i, "no clocks");
}
fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance i) { (void)i; return fmi3OK; }
fmi3Status fmi3UpdateDiscreteStates(fmi3Instance i, fmi3Boolean *needUpdate, fmi3Boolean *terminate,
                                    fmi3Boolean *nominalsChanged, fmi3Boolean *valuesChanged,
                                    fmi3Boolean *nextDefined, fmi3Float64 *next) {
    Model *m = (Model *)i;
    if (m->c.dirty) update_matrices(&m->c);
    *needUpdate = fmi3False;
    *terminate = fmi3False;
    *nominalsChanged = fmi3False;
    *valuesChanged = fmi3False;
    *nextDefined = fmi3False;
    *next = 0.0;
    return fmi3OK;
}

/* ---------------------------------------------------------------- Model Exchange */
fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance i) { (void)i; return fmi3OK; }
fmi3Status fmi3CompletedIntegratorStep(fmi3Instance i, fmi3Boolean noSetPrior, fmi3Boolean *enter,
                                       fmi3Boolean *terminate) {
    (void)i; (void)noSetPrior;
    *enter = fmi3False;
    *terminate = fmi3False;
    return fmi3OK;
}
fmi3Status fmi3SetTime(fmi3Instance i, fmi3Float64 t) { ((Model *)i)->c.time = t; return fmi3OK; }
fmi3Status fmi3SetContinuousStates(fmi3Instance i, const fmi3Float64 x[], size_t n) {
    Model *m = (Model *)i;
    if (n != NX) return fail(m, "fmi3SetContinuousStates: wrong number of states");
    memcpy(m->c.x, x, sizeof(double) * NX);
    return fmi3OK;
}
fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance i, fmi3Float64 dx[], size_t n) {
    Model *m = (Model *)i;
    size_t k;
    if (n != NX) return fail(m, "fmi3GetContinuousStateDerivatives: wrong number of states");
    for (k = 0; k < n; k++) dx[k] = derivative(&m->c, (int)k);
    return fmi3OK;
}
fmi3Status fmi3GetEventIndicators(fmi3Instance i, fmi3Float64 z[], size_t n) {
    (void)z;
    return n ? fail((Model *)i, "no event indicators") : fmi3OK;
}
fmi3Status fmi3GetContinuousStates(fmi3Instance i, fmi3Float64 x[], size_t n) {
    Model *m = (Model *)i;
    if (n != NX) return fail(m, "fmi3GetContinuousStates: wrong number of states");
    memcpy(x, m->c.x, sizeof(double) * NX);
    return fmi3OK;
}
fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance i, fmi3Float64 x[], size_t n) {
    size_t k;
    if (n != NX) return fail((Model *)i, "wrong number of states");
    for (k = 0; k < n; k++) x[k] = NOMINAL[k];
    return fmi3OK;
}
fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance i, size_t *n) { (void)i; *n = 0; return fmi3OK; }
fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance i, size_t *n) { (void)i; *n = NX; return fmi3OK; }

/* ---------------------------------------------------------------- Co-Simulation */
fmi3Status fmi3EnterStepMode(fmi3Instance i) {
    Model *m = (Model *)i;
    if (m->c.dirty) update_matrices(&m->c);
    return fmi3OK;
}
fmi3Status fmi3GetOutputDerivatives(fmi3Instance i, const fmi3ValueReference vr[], size_t nvr,
                                    const fmi3Int32 orders[], fmi3Float64 v[], size_t nv) {
    (void)vr; (void)orders; (void)v; (void)nv;
    return nvr ? fail((Model *)i, "output derivatives not provided") : fmi3OK;
}
fmi3Status fmi3DoStep(fmi3Instance i, fmi3Float64 t, fmi3Float64 h, fmi3Boolean noSetPrior,
                      fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminate,
                      fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime) {
    Model *m = (Model *)i;
    const char *why;
    (void)noSetPrior;
    m->c.time = t;
    why = core_step(&m->c, h);
    *eventHandlingNeeded = fmi3False;
    *terminate = fmi3False;
    *earlyReturn = fmi3False;
    *lastSuccessfulTime = m->c.time;
    return why ? fail(m, why) : fmi3OK;
}
fmi3Status fmi3ActivateModelPartition(fmi3Instance i, fmi3ValueReference clock, fmi3Float64 t) {
    (void)clock; (void)t;
    return fail((Model *)i, "Scheduled Execution is not provided");
}
