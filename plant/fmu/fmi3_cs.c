/* FMI 3.0 Co-Simulation wrapper around the CasADi-generated wheelset step (railway-hil, plant/fmu).
 *
 * Same model, same variables and same stepping as fmi2_cs.c (read that file first); only the FMI 3
 * calling conventions differ: one value-reference space for all types (fault_active and the
 * independent variable time follow the reals), malloc instead of memory callbacks, and fmi3DoStep's
 * extra results.  Functions of the other interface types and of unsupported capabilities are
 * present (FMI 3 requires every function to be exported) and return fmi3Error.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "model_spec.h"
#include "wheelset_model.h"

#define VR3_FAULT_ACTIVE N_REAL
#define VR3_TIME (N_REAL + 1)

typedef enum { ST_INSTANTIATED, ST_INIT, ST_STEP, ST_TERMINATED, ST_ERROR } ModelState;

typedef struct {
    fmi3InstanceEnvironment env;
    fmi3LogMessageCallback log;
    char name[128];
    fmi3Boolean logging;
    ModelState state;
    double r[N_REAL];
    fmi3Boolean fault_active;
    double x[2];
    double time_s;
    const casadi_real *arg[16];
    casadi_real *res[16];
    casadi_int *iw;
    casadi_real *w;
} Model;

static fmi3Status fail(Model *m, const char *fmt, ...) {
    char buf[400];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    if (m && m->log) m->log(m->env, fmi3Error, "logStatusError", buf);
    return fmi3Error;
}

static fmi3Status unsupported(fmi3Instance instance, const char *what) {
    return fail((Model *)instance, "%s is not supported by this FMU", what);
}

static int update_outputs(Model *m) {
    double out[3];
    m->arg[0] = m->x;
    m->arg[1] = &m->time_s;
    m->arg[2] = m->r;
    m->res[0] = &out[0];
    m->res[1] = &out[1];
    m->res[2] = &out[2];
    if (OUT_FN(m->arg, m->res, m->iw, m->w, 0)) return 1;
    m->r[VR_OMEGA] = m->x[0];
    m->r[VR_V] = m->x[1];
    m->r[VR_MU] = out[0];
    m->r[VR_CREEP] = out[1];
    m->r[VR_LOAD] = out[2];
    m->fault_active = m->time_s >= m->r[VR_FAULT_TIME];
    return 0;
}

static void load_initial_state(Model *m) {
    m->x[0] = m->r[VR_OMEGA0];
    m->x[1] = m->r[VR_V0];
}

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[]) {
    (void)nCategories; (void)categories;
    ((Model *)instance)->logging = loggingOn;
    return fmi3OK;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    if (logMessage) logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                               "this FMU supports Co-Simulation only");
    return NULL;
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken,
                                               fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                               fmi3InstanceEnvironment instanceEnvironment,
                                               fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lockPreemption,
                                               fmi3UnlockPreemptionCallback unlockPreemption) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    (void)clockUpdate; (void)lockPreemption; (void)unlockPreemption;
    if (logMessage) logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                               "this FMU supports Co-Simulation only");
    return NULL;
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
                                         fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                         fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference requiredIntermediateVariables[],
                                         size_t nRequiredIntermediateVariables,
                                         fmi3InstanceEnvironment instanceEnvironment,
                                         fmi3LogMessageCallback logMessage,
                                         fmi3IntermediateUpdateCallback intermediateUpdate) {
    (void)resourcePath; (void)visible; (void)earlyReturnAllowed; (void)requiredIntermediateVariables;
    (void)nRequiredIntermediateVariables; (void)intermediateUpdate;
    Model *m = (Model *)calloc(1, sizeof(Model));
    if (!m) return NULL;
    m->env = instanceEnvironment;
    m->log = logMessage;
    m->logging = loggingOn;
    snprintf(m->name, sizeof m->name, "%s", instanceName ? instanceName : "wheelset");
    if (eventModeUsed) {
        fail(m, "event mode is not supported (hasEventMode=false)");
        free(m);
        return NULL;
    }
    if (!instantiationToken || strcmp(instantiationToken, MODEL_GUID) != 0) {
        fail(m, "instantiationToken mismatch: modelDescription.xml and binary are from different exports");
        free(m);
        return NULL;
    }
    casadi_int sz_arg, sz_res, sz_iw, sz_w, a2, r2, iw2, w2;
    STEP_FN_WORK(&sz_arg, &sz_res, &sz_iw, &sz_w);
    OUT_FN_WORK(&a2, &r2, &iw2, &w2);
    if (a2 > sz_arg) sz_arg = a2;
    if (r2 > sz_res) sz_res = r2;
    if (iw2 > sz_iw) sz_iw = iw2;
    if (w2 > sz_w) sz_w = w2;
    m->iw = (casadi_int *)calloc((size_t)(sz_iw + 1), sizeof(casadi_int));
    m->w = (casadi_real *)calloc((size_t)(sz_w + 1), sizeof(casadi_real));
    if (sz_arg > 16 || sz_res > 16 || !m->iw || !m->w) {
        free(m->iw);
        free(m->w);
        free(m);
        return NULL;
    }
    memcpy(m->r, START_VALUES, sizeof m->r);
    m->state = ST_INSTANTIATED;
    return m;
}

void fmi3FreeInstance(fmi3Instance instance) {
    Model *m = (Model *)instance;
    if (!m) return;
    free(m->iw);
    free(m->w);
    free(m);
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
                                       fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    Model *m = (Model *)instance;
    if (m->state != ST_INSTANTIATED) return fail(m, "fmi3EnterInitializationMode: only allowed after instantiation");
    m->time_s = startTime;
    m->state = ST_INIT;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) {
    Model *m = (Model *)instance;
    if (m->state != ST_INIT) return fail(m, "fmi3ExitInitializationMode: not in initialization mode");
    if (!(m->r[VR_H] > 0)) return fail(m, "integration_step_s must be > 0, got %g", m->r[VR_H]);
    load_initial_state(m);
    if (update_outputs(m)) return fail(m, "output evaluation failed");
    m->state = ST_STEP;
    return fmi3OK;
}

fmi3Status fmi3EnterStepMode(fmi3Instance instance) {
    Model *m = (Model *)instance;
    return m->state == ST_STEP ? fmi3OK : fail(m, "fmi3EnterStepMode: not initialised");
}

fmi3Status fmi3Terminate(fmi3Instance instance) {
    ((Model *)instance)->state = ST_TERMINATED;
    return fmi3OK;
}

fmi3Status fmi3Reset(fmi3Instance instance) {
    Model *m = (Model *)instance;
    memcpy(m->r, START_VALUES, sizeof m->r);
    m->fault_active = false;
    m->time_s = 0;
    m->state = ST_INSTANTIATED;
    return fmi3OK;
}

fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, fmi3Float64 values[], size_t nValues) {
    Model *m = (Model *)instance;
    if (nValues < nValueReferences) return fail(m, "fmi3GetFloat64: nValues < nValueReferences");
    if (m->state == ST_INIT) {
        load_initial_state(m);
        if (update_outputs(m)) return fail(m, "output evaluation failed");
    }
    for (size_t i = 0; i < nValueReferences; i++) {
        fmi3ValueReference k = valueReferences[i];
        if (k == VR3_TIME) values[i] = m->time_s;
        else if (k < N_REAL) values[i] = m->r[k];
        else return fail(m, "fmi3GetFloat64: unknown Float64 value reference %u", k);
    }
    return fmi3OK;
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, const fmi3Float64 values[], size_t nValues) {
    Model *m = (Model *)instance;
    if (nValues < nValueReferences) return fail(m, "fmi3SetFloat64: nValues < nValueReferences");
    for (size_t i = 0; i < nValueReferences; i++) {
        fmi3ValueReference k = valueReferences[i];
        if (k > VR_TORQUE) return fail(m, "fmi3SetFloat64: value reference %u is not a parameter or input", k);
        if (k < VR_TORQUE && m->state != ST_INSTANTIATED && m->state != ST_INIT)
            return fail(m, "fmi3SetFloat64: parameter (value reference %u) is fixed after initialisation", k);
        m->r[k] = values[i];
    }
    return fmi3OK;
}

fmi3Status fmi3GetBoolean(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, fmi3Boolean values[], size_t nValues) {
    Model *m = (Model *)instance;
    if (nValues < nValueReferences) return fail(m, "fmi3GetBoolean: nValues < nValueReferences");
    if (m->state == ST_INIT) {
        load_initial_state(m);
        if (update_outputs(m)) return fail(m, "output evaluation failed");
    }
    for (size_t i = 0; i < nValueReferences; i++) {
        if (valueReferences[i] != VR3_FAULT_ACTIVE)
            return fail(m, "fmi3GetBoolean: unknown Boolean value reference %u", valueReferences[i]);
        values[i] = m->fault_active;
    }
    return fmi3OK;
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint,
                      fmi3Float64 communicationStepSize, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                      fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn,
                      fmi3Float64 *lastSuccessfulTime) {
    (void)noSetFMUStatePriorToCurrentPoint;
    Model *m = (Model *)instance;
    if (eventHandlingNeeded) *eventHandlingNeeded = false;
    if (terminateSimulation) *terminateSimulation = false;
    if (earlyReturn) *earlyReturn = false;
    if (lastSuccessfulTime) *lastSuccessfulTime = m->time_s;
    if (m->state != ST_STEP) return fail(m, "fmi3DoStep: not initialised or already terminated");
    const double h = m->r[VR_H];
    const double ratio = communicationStepSize / h;
    const long n = lround(ratio);
    if (n < 1 || fabs(ratio - (double)n) > 1e-6 * (double)n)
        return fail(m, "fmi3DoStep: communication step %g s is not a whole multiple of integration_step_s %g s",
                    communicationStepSize, h);
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
        if (STEP_FN(m->arg, m->res, m->iw, m->w, 0)) return fail(m, "RK4 step failed at t = %g s", t);
        m->x[0] = xn[0];
        m->x[1] = xn[1];
    }
    m->time_s = t0 + (double)n * h;
    if (!isfinite(m->x[0]) || !isfinite(m->x[1])) {
        m->state = ST_ERROR;
        return fail(m, "plant diverged at t = %g s (torque %g N.m)", m->time_s, m->r[VR_TORQUE]);
    }
    if (update_outputs(m)) return fail(m, "output evaluation failed");
    if (lastSuccessfulTime) *lastSuccessfulTime = m->time_s;
    return fmi3OK;
}

/* ---- everything else: present, unsupported ---------------------------------------------------- */
fmi3Status fmi3EnterEventMode(fmi3Instance instance) { return unsupported(instance, "fmi3EnterEventMode"); }
fmi3Status fmi3GetFloat32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float32 values[], size_t nValues) { return unsupported(instance, "fmi3GetFloat32"); }
fmi3Status fmi3GetInt8(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Int8 values[], size_t nValues) { return unsupported(instance, "fmi3GetInt8"); }
fmi3Status fmi3GetUInt8(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt8 values[], size_t nValues) { return unsupported(instance, "fmi3GetUInt8"); }
fmi3Status fmi3GetInt16(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Int16 values[], size_t nValues) { return unsupported(instance, "fmi3GetInt16"); }
fmi3Status fmi3GetUInt16(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt16 values[], size_t nValues) { return unsupported(instance, "fmi3GetUInt16"); }
fmi3Status fmi3GetInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Int32 values[], size_t nValues) { return unsupported(instance, "fmi3GetInt32"); }
fmi3Status fmi3GetUInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt32 values[], size_t nValues) { return unsupported(instance, "fmi3GetUInt32"); }
fmi3Status fmi3GetInt64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Int64 values[], size_t nValues) { return unsupported(instance, "fmi3GetInt64"); }
fmi3Status fmi3GetUInt64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 values[], size_t nValues) { return unsupported(instance, "fmi3GetUInt64"); }
fmi3Status fmi3GetString(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3String values[], size_t nValues) { return unsupported(instance, "fmi3GetString"); }
fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, size_t valueSizes[], fmi3Binary values[], size_t nValues) { return unsupported(instance, "fmi3GetBinary"); }
fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Clock values[]) { return unsupported(instance, "fmi3GetClock"); }
fmi3Status fmi3SetFloat32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float32 values[], size_t nValues) { return unsupported(instance, "fmi3SetFloat32"); }
fmi3Status fmi3SetInt8(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int8 values[], size_t nValues) { return unsupported(instance, "fmi3SetInt8"); }
fmi3Status fmi3SetUInt8(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt8 values[], size_t nValues) { return unsupported(instance, "fmi3SetUInt8"); }
fmi3Status fmi3SetInt16(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int16 values[], size_t nValues) { return unsupported(instance, "fmi3SetInt16"); }
fmi3Status fmi3SetUInt16(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt16 values[], size_t nValues) { return unsupported(instance, "fmi3SetUInt16"); }
fmi3Status fmi3SetInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int32 values[], size_t nValues) { return unsupported(instance, "fmi3SetInt32"); }
fmi3Status fmi3SetUInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt32 values[], size_t nValues) { return unsupported(instance, "fmi3SetUInt32"); }
fmi3Status fmi3SetInt64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int64 values[], size_t nValues) { return unsupported(instance, "fmi3SetInt64"); }
fmi3Status fmi3SetUInt64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 values[], size_t nValues) { return unsupported(instance, "fmi3SetUInt64"); }
fmi3Status fmi3SetBoolean(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Boolean values[], size_t nValues) { return unsupported(instance, "fmi3SetBoolean"); }
fmi3Status fmi3SetString(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3String values[], size_t nValues) { return unsupported(instance, "fmi3SetString"); }
fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const size_t valueSizes[], const fmi3Binary values[], size_t nValues) { return unsupported(instance, "fmi3SetBinary"); }
fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Clock values[]) { return unsupported(instance, "fmi3SetClock"); }
fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference, size_t* nDependencies) { return unsupported(instance, "fmi3GetNumberOfVariableDependencies"); }
fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent, size_t elementIndicesOfDependent[], fmi3ValueReference independents[], size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[], size_t nDependencies) { return unsupported(instance, "fmi3GetVariableDependencies"); }
fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState* FMUState) { return unsupported(instance, "fmi3GetFMUState"); }
fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState) { return unsupported(instance, "fmi3SetFMUState"); }
fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState* FMUState) { return unsupported(instance, "fmi3FreeFMUState"); }
fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t* size) { return unsupported(instance, "fmi3SerializedFMUStateSize"); }
fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[], size_t size) { return unsupported(instance, "fmi3SerializeFMUState"); }
fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size, fmi3FMUState* FMUState) { return unsupported(instance, "fmi3DeserializeFMUState"); }
fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns, const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) { return unsupported(instance, "fmi3GetDirectionalDerivative"); }
fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns, const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) { return unsupported(instance, "fmi3GetAdjointDerivative"); }
fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) { return unsupported(instance, "fmi3EnterConfigurationMode"); }
fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) { return unsupported(instance, "fmi3ExitConfigurationMode"); }
fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[]) { return unsupported(instance, "fmi3GetIntervalDecimal"); }
fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[], fmi3IntervalQualifier qualifiers[]) { return unsupported(instance, "fmi3GetIntervalFraction"); }
fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float64 shifts[]) { return unsupported(instance, "fmi3GetShiftDecimal"); }
fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[]) { return unsupported(instance, "fmi3GetShiftFraction"); }
fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float64 intervals[]) { return unsupported(instance, "fmi3SetIntervalDecimal"); }
fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) { return unsupported(instance, "fmi3SetIntervalFraction"); }
fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float64 shifts[]) { return unsupported(instance, "fmi3SetShiftDecimal"); }
fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) { return unsupported(instance, "fmi3SetShiftFraction"); }
fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) { return unsupported(instance, "fmi3EvaluateDiscreteStates"); }
fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean* discreteStatesNeedUpdate, fmi3Boolean* terminateSimulation, fmi3Boolean* nominalsOfContinuousStatesChanged, fmi3Boolean* valuesOfContinuousStatesChanged, fmi3Boolean* nextEventTimeDefined, fmi3Float64* nextEventTime) { return unsupported(instance, "fmi3UpdateDiscreteStates"); }
fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance) { return unsupported(instance, "fmi3EnterContinuousTimeMode"); }
fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean* enterEventMode, fmi3Boolean* terminateSimulation) { return unsupported(instance, "fmi3CompletedIntegratorStep"); }
fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time) { return unsupported(instance, "fmi3SetTime"); }
fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 continuousStates[], size_t nContinuousStates) { return unsupported(instance, "fmi3SetContinuousStates"); }
fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 derivatives[], size_t nContinuousStates) { return unsupported(instance, "fmi3GetContinuousStateDerivatives"); }
fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 eventIndicators[], size_t nEventIndicators) { return unsupported(instance, "fmi3GetEventIndicators"); }
fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 continuousStates[], size_t nContinuousStates) { return unsupported(instance, "fmi3GetContinuousStates"); }
fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[], size_t nContinuousStates) { return unsupported(instance, "fmi3GetNominalsOfContinuousStates"); }
fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t* nEventIndicators) { return unsupported(instance, "fmi3GetNumberOfEventIndicators"); }
fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t* nContinuousStates) { return unsupported(instance, "fmi3GetNumberOfContinuousStates"); }
fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int32 orders[], fmi3Float64 values[], size_t nValues) { return unsupported(instance, "fmi3GetOutputDerivatives"); }
fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference, fmi3Float64 activationTime) { return unsupported(instance, "fmi3ActivateModelPartition"); }
