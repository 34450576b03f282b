/* FMI 2.0 Model Exchange + Co-Simulation functions of the model above (fmu_core.c).
 *
 * Build (any C99 compiler, the FMI 2.0 headers on the include path, e.g. the c-code
 * folder of fmpy or of the FMI standard):
 *
 *     cc -std=c99 -O2 -shared -fPIC -I<fmi2 headers> -o <modelIdentifier>.so fmu.c -lm
 *
 * Value references: 0..NX-1 states x, NX..2NX-1 their derivatives, then NU inputs u, NY
 * outputs y and NPAR parameters (damping ratios, then the filter cut-off in Hz).
 */
#include "fmi2Functions.h"

#define VR_X 0
#define VR_DX (NX)
#define VR_U (2 * NX)
#define VR_Y (2 * NX + NU)
#define VR_P (2 * NX + NU + NY)
#define VR_END (2 * NX + NU + NY + NPAR)

typedef struct {
    Core c;
    fmi2Type type;
    fmi2CallbackFunctions cb;
    char *name;
} Model;

static void log_error(Model *m, const char *msg) {
    if (m && m->cb.logger)
        m->cb.logger(m->cb.componentEnvironment, m->name, fmi2Error, "logStatusError", "%s", msg);
}

/* ---------------------------------------------------------------- FMI 2.0 functions */
const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cat[]) {
    (void)c; (void)on; (void)n; (void)cat;
    return fmi2OK;
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
    reset_core(&m->c);
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
    ((Model *)c)->c.time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Model *m = (Model *)c;
    if (m->c.dirty) update_matrices(&m->c);
    return fmi2OK;
}
fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2Reset(fmi2Component c) { reset_core(&((Model *)c)->c); return fmi2OK; }

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real v[]) {
    Model *m = (Model *)c;
    size_t i;
    for (i = 0; i < n; i++) {
        const fmi2ValueReference r = vr[i];
        if (r < VR_DX) v[i] = m->c.x[r - VR_X];
        else if (r < VR_U) v[i] = derivative(&m->c, (int)(r - VR_DX));
        else if (r < VR_Y) v[i] = m->c.u[r - VR_U];
        else if (r < VR_P) v[i] = output(&m->c, (int)(r - VR_Y));
        else if (r < VR_END) v[i] = m->c.par[r - VR_P];
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
        if (r < VR_DX) m->c.x[r] = v[i];
        else if (r >= VR_U && r < VR_Y) m->c.u[r - VR_U] = v[i];
        else if (r >= VR_P && r < VR_END) {
            const char *why = set_parameter(&m->c, (int)(r - VR_P), v[i]);
            if (why) { log_error(m, why); return fmi2Error; }
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
fmi2Status fmi2SetTime(fmi2Component c, fmi2Real t) { ((Model *)c)->c.time = t; return fmi2OK; }
fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t n) {
    Model *m = (Model *)c;
    if (n != NX) { log_error(m, "fmi2SetContinuousStates: wrong number of states"); return fmi2Error; }
    memcpy(m->c.x, x, sizeof(double) * NX);
    return fmi2OK;
}
fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t n) {
    Model *m = (Model *)c;
    size_t i;
    if (n != NX) { log_error(m, "fmi2GetDerivatives: wrong number of states"); return fmi2Error; }
    for (i = 0; i < n; i++) dx[i] = derivative(&m->c, (int)i);
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
    memcpy(x, m->c.x, sizeof(double) * NX);
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
    const char *why;
    (void)noSetPrior;
    m->c.time = t;
    why = core_step(&m->c, h);
    if (why) { log_error(m, why); return fmi2Error; }
    return fmi2OK;
}
fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }
fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v) {
    (void)c; (void)s; *v = fmi2OK; return fmi2OK;
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    if (s == fmi2LastSuccessfulTime) { *v = ((Model *)c)->c.time; return fmi2OK; }
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
