/* FMI 2.0 Co-Simulation wrapper around the CasADi-generated wheelset step (railway-hil, plant/fmu).
 *
 * The physics is not written here: it is CasADi C code generated from plant.model.dynamics() and
 * plant.model.rk4_step(), the same expressions the Python loop integrates.  This file only keeps the
 * variables, checks the FMI calling sequence, and in fmi2DoStep runs as many fixed RK4 steps of
 * integration_step_s as the communication step holds.
 *
 * model_spec.h (generated next to this file) defines the value references, the start values and
 * the names of the two generated functions:
 *   STEP_FN(x[2], torque_nm, t_s, h_s, p[N_MODEL_PARAMS]) -> x[2]        one RK4 step
 *   OUT_FN(x[2], t_s, p[N_MODEL_PARAMS]) -> mu, creep_speed_kmh, load_torque_nm
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"
#include "model_spec.h"
#include "wheelset_model.h"

typedef enum { ST_INSTANTIATED, ST_INIT, ST_STEP, ST_TERMINATED, ST_ERROR } ModelState;

typedef struct {
    fmi2CallbackFunctions cb;
    char name[128];
    fmi2Boolean logging;
    ModelState state;
    double r[N_REAL];           /* all Real variables by value reference */
    fmi2Boolean b[N_BOOL];      /* all Boolean variables by value reference */
    double x[2];                /* motor speed rad/s, train speed m/s */
    double time_s;
    const casadi_real *arg[16];
    casadi_real *res[16];
    casadi_int *iw;
    casadi_real *w;
} Model;

static void logf_(Model *m, fmi2Status status, const char *fmt, ...) {
    char buf[512];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    if (m->cb.logger && (m->logging || status >= fmi2Warning))
        m->cb.logger(m->cb.componentEnvironment, m->name, status, status >= fmi2Error ? "logStatusError" : "logAll",
                     "%s", buf);
}

static fmi2Status fail(Model *m, const char *fmt, ...) {
    char buf[400];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    logf_(m, fmi2Error, "%s", buf);
    return fmi2Error;
}

/* Evaluate the generated output function at the current state and time. */
static int update_outputs(Model *m) {
    double out[3];
    m->arg[0] = m->x;
    m->arg[1] = &m->time_s;
    m->arg[2] = m->r;               /* the model parameters are the first N_MODEL_PARAMS reals */
    m->res[0] = &out[0];
    m->res[1] = &out[1];
    m->res[2] = &out[2];
    if (OUT_FN(m->arg, m->res, m->iw, m->w, 0)) return 1;
    m->r[VR_OMEGA] = m->x[0];
    m->r[VR_V] = m->x[1];
    m->r[VR_MU] = out[0];
    m->r[VR_CREEP] = out[1];
    m->r[VR_LOAD] = out[2];
    m->b[VR_FAULT_ACTIVE] = m->time_s >= m->r[VR_FAULT_TIME] ? fmi2True : fmi2False;
    return 0;
}

static void load_initial_state(Model *m) {
    m->x[0] = m->r[VR_OMEGA0];
    m->x[1] = m->r[VR_V0];
}

/* ---- common functions ------------------------------------------------------------------------ */
const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    (void)nCategories; (void)categories;
    ((Model *)c)->logging = loggingOn;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    (void)fmuResourceLocation; (void)visible;
    if (!functions || !functions->allocateMemory || !functions->freeMemory) return NULL;
    Model *m = (Model *)functions->allocateMemory(1, sizeof(Model));
    if (!m) return NULL;
    memset(m, 0, sizeof(Model));
    m->cb = *functions;
    snprintf(m->name, sizeof m->name, "%s", instanceName ? instanceName : "wheelset");
    m->logging = loggingOn;
    if (fmuType != fmi2CoSimulation) {
        logf_(m, fmi2Error, "this FMU supports Co-Simulation only");
        functions->freeMemory(m);
        return NULL;
    }
    if (!fmuGUID || strcmp(fmuGUID, MODEL_GUID) != 0) {
        logf_(m, fmi2Error, "GUID mismatch: modelDescription.xml and binary are from different exports");
        functions->freeMemory(m);
        return NULL;
    }
    casadi_int sz_arg, sz_res, sz_iw, sz_w, a2, r2, iw2, w2;
    STEP_FN_WORK(&sz_arg, &sz_res, &sz_iw, &sz_w);
    OUT_FN_WORK(&a2, &r2, &iw2, &w2);
    if (a2 > sz_arg) sz_arg = a2;
    if (r2 > sz_res) sz_res = r2;
    if (iw2 > sz_iw) sz_iw = iw2;
    if (w2 > sz_w) sz_w = w2;
    if (sz_arg > 16 || sz_res > 16) {
        logf_(m, fmi2Error, "generated functions need more argument slots than the wrapper has");
        functions->freeMemory(m);
        return NULL;
    }
    m->iw = (casadi_int *)functions->allocateMemory((size_t)(sz_iw + 1), sizeof(casadi_int));
    m->w = (casadi_real *)functions->allocateMemory((size_t)(sz_w + 1), sizeof(casadi_real));
    if (!m->iw || !m->w) {
        if (m->iw) functions->freeMemory(m->iw);
        if (m->w) functions->freeMemory(m->w);
        functions->freeMemory(m);
        return NULL;
    }
    memcpy(m->r, START_VALUES, sizeof m->r);
    m->b[VR_FAULT_ACTIVE] = fmi2False;
    m->state = ST_INSTANTIATED;
    return m;
}

void fmi2FreeInstance(fmi2Component c) {
    Model *m = (Model *)c;
    if (!m) return;
    fmi2CallbackFreeMemory freeMemory = m->cb.freeMemory;
    freeMemory(m->iw);
    freeMemory(m->w);
    freeMemory(m);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    Model *m = (Model *)c;
    if (m->state != ST_INSTANTIATED) return fail(m, "%s: only allowed after fmi2Instantiate",
                                                  "fmi2SetupExperiment");
    m->time_s = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    Model *m = (Model *)c;
    if (m->state != ST_INSTANTIATED) return fail(m, "%s: only allowed after fmi2Instantiate",
                                                  "fmi2EnterInitializationMode");
    m->state = ST_INIT;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Model *m = (Model *)c;
    if (m->state != ST_INIT) return fail(m, "%s: not in initialization mode", "fmi2ExitInitializationMode");
    if (!(m->r[VR_H] > 0)) return fail(m, "%s must be > 0, got %g", "integration_step_s", m->r[VR_H]);
    load_initial_state(m);
    if (update_outputs(m)) return fail(m, "%s failed", "output evaluation");
    m->state = ST_STEP;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    ((Model *)c)->state = ST_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Model *m = (Model *)c;
    memcpy(m->r, START_VALUES, sizeof m->r);
    m->b[VR_FAULT_ACTIVE] = fmi2False;
    m->time_s = 0;
    m->state = ST_INSTANTIATED;
    return fmi2OK;
}

/* ---- variables --------------------------------------------------------------------------------- */
fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    Model *m = (Model *)c;
    if (m->state == ST_INIT) {      /* outputs during initialisation: from the initial-state parameters */
        load_initial_state(m);
        if (update_outputs(m)) return fail(m, "%s failed", "output evaluation");
    }
    for (size_t i = 0; i < nvr; i++) {
        if (vr[i] >= N_REAL) return fail(m, "%s: unknown Real value reference %u", "fmi2GetReal", vr[i]);
        value[i] = m->r[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    Model *m = (Model *)c;
    for (size_t i = 0; i < nvr; i++) {
        fmi2ValueReference k = vr[i];
        if (k >= N_REAL || k > VR_TORQUE)
            return fail(m, "%s: value reference %u is not a parameter or input", "fmi2SetReal", k);
        if (k < VR_TORQUE && m->state != ST_INSTANTIATED && m->state != ST_INIT)
            return fail(m, "%s: parameter (value reference %u) is fixed after initialisation",
                        "fmi2SetReal", k);
        m->r[k] = value[i];
    }
    return fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    Model *m = (Model *)c;
    if (m->state == ST_INIT) {
        load_initial_state(m);
        if (update_outputs(m)) return fail(m, "%s failed", "output evaluation");
    }
    for (size_t i = 0; i < nvr; i++) {
        if (vr[i] >= N_BOOL) return fail(m, "%s: unknown Boolean value reference %u", "fmi2GetBoolean",
                                         vr[i]);
        value[i] = m->b[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    (void)value;
    return nvr ? fail((Model *)c, "%s: this FMU has no Integer variables (value reference %u)",
                      "fmi2GetInteger", vr[0]) : fmi2OK;
}
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    (void)value;
    return nvr ? fail((Model *)c, "%s: this FMU has no String variables (value reference %u)",
                      "fmi2GetString", vr[0]) : fmi2OK;
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    (void)value;
    return nvr ? fail((Model *)c, "%s: this FMU has no Integer variables (value reference %u)",
                      "fmi2SetInteger", vr[0]) : fmi2OK;
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[]) {
    (void)value;
    return nvr ? fail((Model *)c, "%s: Boolean value reference %u is an output", "fmi2SetBoolean", vr[0])
               : fmi2OK;
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    (void)value;
    return nvr ? fail((Model *)c, "%s: this FMU has no String variables (value reference %u)",
                      "fmi2SetString", vr[0]) : fmi2OK;
}

/* ---- FMU state and derivatives: not supported (capability flags say so) ------------------------ */
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)s; return fail((Model *)c, "%s", "fmi2GetFMUstate not supported"); }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { (void)s; return fail((Model *)c, "%s", "fmi2SetFMUstate not supported"); }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)s; return fail((Model *)c, "%s", "fmi2FreeFMUstate not supported"); }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) { (void)s; (void)n; return fail((Model *)c, "%s", "FMU state serialisation not supported"); }
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n) { (void)s; (void)b; (void)n; return fail((Model *)c, "%s", "FMU state serialisation not supported"); }
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *s) { (void)s; (void)b; (void)n; return fail((Model *)c, "%s", "FMU state serialisation not supported"); }
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real dv[], fmi2Real dz[]) {
    (void)u; (void)nu; (void)z; (void)nz; (void)dv; (void)dz;
    return fail((Model *)c, "%s", "directional derivatives not supported");
}

/* ---- co-simulation ------------------------------------------------------------------------------ */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    return fail((Model *)c, "%s", "input derivatives not supported (canInterpolateInputs=false)");
}
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    return fail((Model *)c, "%s", "output derivatives not supported (maxOutputDerivativeOrder=0)");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    (void)noSetFMUStatePriorToCurrentPoint;
    Model *m = (Model *)c;
    if (m->state != ST_STEP) return fail(m, "%s: not initialised or already terminated", "fmi2DoStep");
    const double h = m->r[VR_H];
    const double ratio = communicationStepSize / h;
    const long n = lround(ratio);
    if (n < 1 || fabs(ratio - (double)n) > 1e-6 * (double)n)
        return fail(m, "%s: communication step %g s is not a whole multiple of integration_step_s %g s",
                    "fmi2DoStep", communicationStepSize, h);
    const double t0 = currentCommunicationPoint;
    double xn[2];
    m->arg[1] = &m->r[VR_TORQUE];
    m->arg[3] = &m->r[VR_H];
    m->arg[4] = m->r;
    m->res[0] = xn;
    for (long i = 0; i < n; i++) {
        const double t = t0 + (double)i * h;   /* the same arithmetic as plant.model.build_period_step */
        m->arg[0] = m->x;
        m->arg[2] = &t;
        if (STEP_FN(m->arg, m->res, m->iw, m->w, 0)) return fail(m, "%s failed at t = %g s", "RK4 step", t);
        m->x[0] = xn[0];
        m->x[1] = xn[1];
    }
    m->time_s = t0 + (double)n * h;
    if (!isfinite(m->x[0]) || !isfinite(m->x[1])) {
        m->state = ST_ERROR;
        return fail(m, "%s diverged at t = %g s (torque %g N.m)", "plant", m->time_s, m->r[VR_TORQUE]);
    }
    if (update_outputs(m)) return fail(m, "%s failed", "output evaluation");
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)s; (void)value;
    return fail((Model *)c, "%s", "fmi2GetStatus: no asynchronous steps");
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    Model *m = (Model *)c;
    if (s == fmi2LastSuccessfulTime) { *value = m->time_s; return fmi2OK; }
    return fail(m, "%s", "fmi2GetRealStatus: only fmi2LastSuccessfulTime");
}
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)s; (void)value;
    return fail((Model *)c, "%s", "fmi2GetIntegerStatus not supported");
}
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    (void)s; (void)value;
    return fail((Model *)c, "%s", "fmi2GetBooleanStatus not supported");
}
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)s; (void)value;
    return fail((Model *)c, "%s", "fmi2GetStringStatus not supported");
}
