/* fmi3_controller.c: FMI 3.0 co-simulation wrapper of the sampled controller library
 * (ivdrem_controller.c), shipped in every FMI 3.0 controller FMU that ivdrem exports
 * (ivdrem/controller/fmu_export.py, fmi_version=3).  Sizes, value references and names come
 * from the same generated controller_fmu.h as the FMI 2.0 wrapper fmi2_controller.c, and the
 * behaviour is the same (docs/controller.md): fmi3DoStep(t_k, h) reads q(t_k), dq(t_k) and
 * outputs tau_k from then on (delay 1); the step must equal the sample period h; an illegal
 * call or bad value is logged (category logStatusError) and returns fmi3Error.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "ivdrem_controller.h"
#include "controller_fmu.h"

enum { Instantiated = 1, InitializationMode = 2, StepMode = 4, Terminated = 8, Error = 16 };
#define ANY (Instantiated | InitializationMode | StepMode | Terminated | Error)
#define INSTANCE_MAGIC 0x1D4E3C7Cu

typedef struct {
    int state;
    int has_controller;
    double time;
    double in[2 * IVC_NQ];
    double par[IVC_NPAR];
    size_t csize;
} Head;

typedef struct {
    unsigned int magic;
    Head d;
    ivc_controller *ctl;
    char *instanceName;
    fmi3LogMessageCallback logger;
    fmi3InstanceEnvironment env;
    int logEvents;
} Instance;

static void logMessage(Instance *S, fmi3Status status, const char *category, const char *fmt, ...) {
    char buf[1024];
    va_list args;
    if (!S || !S->logger) return;
    if (status == fmi3OK && !S->logEvents) return;
    va_start(args, fmt);
    vsnprintf(buf, sizeof(buf), fmt, args);
    va_end(args);
    S->logger(S->env, status, category, buf);
}
#define logError(S, ...) logMessage(S, fmi3Error, "logStatusError", __VA_ARGS__)

static int invalidState(Instance *S, const char *f, int mask) {
    if (!S || S->magic != INSTANCE_MAGIC) return 1;
    if (!(S->d.state & mask)) {
        logError(S, "%s: illegal call sequence (not allowed in the current state).", f);
        S->d.state = Error;
        return 1;
    }
    return 0;
}
static fmi3Status fail(Instance *S) { S->d.state = Error; return fmi3Error; }
static int nullPointer(Instance *S, const char *f, const char *arg, const void *p) {
    if (p) return 0;
    logError(S, "%s: invalid argument %s = NULL.", f, arg);
    S->d.state = Error;
    return 1;
}

static void vrName(fmi3ValueReference vr, char *buf, size_t n) {
    if (vr < VR_DQ)              snprintf(buf, n, "q[%u]", vr - VR_Q);
    else if (vr < VR_TAU)        snprintf(buf, n, "dq[%u]", vr - VR_DQ);
    else if (vr < VR_THETA_HAT)  snprintf(buf, n, "tau[%u]", vr - VR_TAU);
    else if (vr < VR_TAU_D_HAT)  snprintf(buf, n, "theta_hat[%u]", vr - VR_THETA_HAT);
    else if (vr < VR_DELTA)      snprintf(buf, n, "tau_d_hat[%u]", vr - VR_TAU_D_HAT);
    else if (vr == VR_DELTA)     snprintf(buf, n, "Delta");
    else if (vr < VR_PAR + IVC_NPAR) snprintf(buf, n, "%s", PARAMETER_NAMES[vr - VR_PAR]);
    else                         snprintf(buf, n, "#%u", vr);
}

static void setStartValues(Instance *S) {
    int i;
    ivc_default_params(S->d.par);
    for (i = 0; i < 2 * IVC_NQ; i++) S->d.in[i] = 0.0;
    S->d.time = 0.0;
}

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
    fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn, fmi3Boolean eventModeUsed,
    fmi3Boolean earlyReturnAllowed, const fmi3ValueReference requiredIntermediateVariables[],
    size_t nRequiredIntermediateVariables, fmi3InstanceEnvironment instanceEnvironment,
    fmi3LogMessageCallback logMessageCb, fmi3IntermediateUpdateCallback intermediateUpdate) {
    Instance tmp, *S;
    (void)resourcePath; (void)visible; (void)earlyReturnAllowed; (void)requiredIntermediateVariables;
    (void)nRequiredIntermediateVariables; (void)intermediateUpdate;
    memset(&tmp, 0, sizeof tmp);
    tmp.logger = logMessageCb;
    tmp.env = instanceEnvironment;
    if (!instanceName || !instanceName[0]) { logError(&tmp, "fmi3InstantiateCoSimulation: missing instance name."); return NULL; }
    if (eventModeUsed) { logError(&tmp, "fmi3InstantiateCoSimulation: event mode is not supported."); return NULL; }
    if (!instantiationToken || strcmp(instantiationToken, MODEL_GUID) != 0) {
        logError(&tmp, "fmi3InstantiateCoSimulation: wrong instantiation token %s, expected %s.",
                 instantiationToken ? instantiationToken : "NULL", MODEL_GUID);
        return NULL;
    }
    S = (Instance *)calloc(1, sizeof(Instance));
    if (!S) return NULL;
    S->instanceName = (char *)calloc(strlen(instanceName) + 1, 1);
    if (!S->instanceName) { free(S); return NULL; }
    strcpy(S->instanceName, instanceName);
    S->logger = tmp.logger;
    S->env = tmp.env;
    S->logEvents = loggingOn ? 1 : 0;
    S->magic = INSTANCE_MAGIC;
    S->d.state = Instantiated;
    setStartValues(S);
    return S;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String a, fmi3String b, fmi3String c, fmi3Boolean d,
    fmi3Boolean e, fmi3InstanceEnvironment env, fmi3LogMessageCallback log) {
    (void)a; (void)b; (void)c; (void)d; (void)e;
    if (log) log(env, fmi3Error, "logStatusError", "the controller is a co-simulation FMU only.");
    return NULL;
}
fmi3Instance fmi3InstantiateScheduledExecution(fmi3String a, fmi3String b, fmi3String c, fmi3Boolean d,
    fmi3Boolean e, fmi3InstanceEnvironment env, fmi3LogMessageCallback log, fmi3ClockUpdateCallback f,
    fmi3LockPreemptionCallback g, fmi3UnlockPreemptionCallback h) {
    (void)a; (void)b; (void)c; (void)d; (void)e; (void)f; (void)g; (void)h;
    if (log) log(env, fmi3Error, "logStatusError", "the controller is a co-simulation FMU only.");
    return NULL;
}

void fmi3FreeInstance(fmi3Instance c) {
    Instance *S = (Instance *)c;
    if (!S || S->magic != INSTANCE_MAGIC) return;
    S->magic = 0;
    ivc_free(S->ctl);
    free(S->instanceName);
    free(S);
}

fmi3Status fmi3SetDebugLogging(fmi3Instance c, fmi3Boolean loggingOn, size_t nCategories, const fmi3String categories[]) {
    Instance *S = (Instance *)c;
    size_t i;
    if (invalidState(S, "fmi3SetDebugLogging", ANY)) return fmi3Error;
    if (nCategories > 0 && nullPointer(S, "fmi3SetDebugLogging", "categories", categories)) return fmi3Error;
    for (i = 0; i < nCategories; i++)
        if (!categories[i] || (strcmp(categories[i], "logEvents") != 0 && strcmp(categories[i], "logStatusError") != 0)) {
            logError(S, "fmi3SetDebugLogging: unknown log category %s.", categories[i] ? categories[i] : "NULL");
            return fail(S);
        }
    S->logEvents = loggingOn ? 1 : 0;
    return fmi3OK;
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance c, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
    fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    Instance *S = (Instance *)c;
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    if (invalidState(S, "fmi3EnterInitializationMode", Instantiated)) return fmi3Error;
    if (startTime != 0.0) {
        logError(S, "fmi3EnterInitializationMode: the controller starts at t = 0 (its mu(t), F(t) and "
                    "reference are functions of t), got start time %g.", startTime);
        return fail(S);
    }
    S->d.state = InitializationMode;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance c) {
    Instance *S = (Instance *)c;
    char msg[256];
    if (invalidState(S, "fmi3ExitInitializationMode", InitializationMode)) return fmi3Error;
    ivc_free(S->ctl);
    S->ctl = ivc_init(S->d.par, msg, sizeof msg);
    if (!S->ctl) { logError(S, "fmi3ExitInitializationMode: %s.", msg); return fail(S); }
    S->d.has_controller = 1;
    S->d.time = 0.0;
    S->d.state = StepMode;
    return fmi3OK;
}

fmi3Status fmi3Terminate(fmi3Instance c) {
    Instance *S = (Instance *)c;
    if (invalidState(S, "fmi3Terminate", StepMode)) return fmi3Error;
    S->d.state = Terminated;
    return fmi3OK;
}

fmi3Status fmi3Reset(fmi3Instance c) {
    Instance *S = (Instance *)c;
    if (invalidState(S, "fmi3Reset", ANY)) return fmi3Error;
    ivc_free(S->ctl);
    S->ctl = NULL;
    S->d.has_controller = 0;
    setStartValues(S);
    S->d.state = Instantiated;
    return fmi3OK;
}

fmi3Status fmi3GetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Float64 value[], size_t nValues) {
    Instance *S = (Instance *)c;
    double th[IVC_NTHETA], tdh[IVC_NQ], D = 0.0, tau[IVC_NQ];
    size_t i;
    if (invalidState(S, "fmi3GetFloat64", InitializationMode | StepMode | Terminated | Error)) return fmi3Error;
    if (nValues != nvr) { logError(S, "fmi3GetFloat64: %lu values for %lu scalar variables.", (unsigned long)nValues, (unsigned long)nvr); return fail(S); }
    if (nvr > 0 && (nullPointer(S, "fmi3GetFloat64", "vr[]", vr) || nullPointer(S, "fmi3GetFloat64", "value[]", value))) return fmi3Error;
    if (S->ctl) ivc_outputs(S->ctl, th, tdh, &D, tau);
    else {
        for (i = 0; i < IVC_NTHETA; i++) th[i] = S->d.par[IVC_P_THETA_HAT0 + i];
        for (i = 0; i < IVC_NQ; i++) tdh[i] = tau[i] = 0.0;
    }
    for (i = 0; i < nvr; i++) {
        fmi3ValueReference r = vr[i];
        if (r < VR_TAU) value[i] = S->d.in[r];
        else if (r < VR_THETA_HAT) value[i] = tau[r - VR_TAU];
        else if (r < VR_TAU_D_HAT) value[i] = th[r - VR_THETA_HAT];
        else if (r < VR_DELTA) value[i] = tdh[r - VR_TAU_D_HAT];
        else if (r == VR_DELTA) value[i] = D;
        else if (r < VR_PAR + IVC_NPAR) value[i] = S->ctl ? ivc_get_param(S->ctl, (int)(r - VR_PAR)) : S->d.par[r - VR_PAR];
        else if (r == VR_TIME) value[i] = S->d.time;     /* the independent variable */
        else { logError(S, "fmi3GetFloat64: unknown value reference %u.", r); return fail(S); }
    }
    return fmi3OK;
}

fmi3Status fmi3SetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Float64 value[], size_t nValues) {
    Instance *S = (Instance *)c;
    char name[64];
    size_t i;
    if (invalidState(S, "fmi3SetFloat64", Instantiated | InitializationMode | StepMode)) return fmi3Error;
    if (nValues != nvr) { logError(S, "fmi3SetFloat64: %lu values for %lu scalar variables.", (unsigned long)nValues, (unsigned long)nvr); return fail(S); }
    if (nvr > 0 && (nullPointer(S, "fmi3SetFloat64", "vr[]", vr) || nullPointer(S, "fmi3SetFloat64", "value[]", value))) return fmi3Error;
    for (i = 0; i < nvr; i++) {
        fmi3ValueReference r = vr[i];
        vrName(r, name, sizeof name);
        if (r < VR_TAU) {
            if (!isfinite(value[i])) { logError(S, "fmi3SetFloat64: %s = %g is not finite.", name, value[i]); return fail(S); }
            S->d.in[r] = value[i];
        } else if (r >= VR_PAR && r < VR_PAR + IVC_NPAR) {
            int k = (int)(r - VR_PAR);
            if (!PARAMETER_EXPOSED[k]) { logError(S, "fmi3SetFloat64: %s is fixed in this FMU.", name); return fail(S); }
            if (isnan(value[i])) { logError(S, "fmi3SetFloat64: %s is NaN.", name); return fail(S); }
            if (S->d.state == StepMode) {
                if (!PARAMETER_TUNABLE[k]) { logError(S, "fmi3SetFloat64: parameter %s is fixed after initialization.", name); return fail(S); }
                if (ivc_set_param(S->ctl, k, value[i]) != IVC_OK) {
                    logError(S, "fmi3SetFloat64: %s = %g refused: %s.", name, value[i], ivc_message(S->ctl));
                    return fail(S);
                }
            }
            S->d.par[k] = value[i];
        } else { logError(S, "fmi3SetFloat64: %s cannot be set (an output or unknown).", name); return fail(S); }
    }
    return fmi3OK;
}

static fmi3Status noSuchVariables(Instance *S, const char *f, size_t nvr) {
    if (invalidState(S, f, ANY)) return fmi3Error;
    if (nvr == 0) return fmi3OK;
    logError(S, "%s: the FMU has no variables of this type.", f);
    return fail(S);
}
#define NO_GET(T, TYPE) fmi3Status fmi3Get##T(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, TYPE value[], size_t nValues) \
    { (void)vr; (void)value; (void)nValues; return noSuchVariables((Instance *)c, "fmi3Get" #T, nvr); }
#define NO_SET(T, TYPE) fmi3Status fmi3Set##T(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const TYPE value[], size_t nValues) \
    { (void)vr; (void)value; (void)nValues; return noSuchVariables((Instance *)c, "fmi3Set" #T, nvr); }
#define NO_GETSET(T, TYPE) NO_GET(T, TYPE) NO_SET(T, TYPE)
NO_GETSET(Float32, fmi3Float32) NO_GETSET(Int8, fmi3Int8) NO_GETSET(UInt8, fmi3UInt8)
NO_GETSET(Int16, fmi3Int16) NO_GETSET(UInt16, fmi3UInt16) NO_GETSET(Int32, fmi3Int32)
NO_GETSET(UInt32, fmi3UInt32) NO_GETSET(Int64, fmi3Int64) NO_GETSET(UInt64, fmi3UInt64)
NO_GETSET(Boolean, fmi3Boolean) NO_GETSET(String, fmi3String)

fmi3Status fmi3GetBinary(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, size_t valueSizes[], fmi3Binary value[], size_t nValues)
    { (void)vr; (void)valueSizes; (void)value; (void)nValues; return noSuchVariables((Instance *)c, "fmi3GetBinary", nvr); }
fmi3Status fmi3SetBinary(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const size_t valueSizes[], const fmi3Binary value[], size_t nValues)
    { (void)vr; (void)valueSizes; (void)value; (void)nValues; return noSuchVariables((Instance *)c, "fmi3SetBinary", nvr); }
fmi3Status fmi3GetClock(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Clock values[])
    { (void)vr; (void)values; return noSuchVariables((Instance *)c, "fmi3GetClock", nvr); }
fmi3Status fmi3SetClock(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Clock values[])
    { (void)vr; (void)values; return noSuchVariables((Instance *)c, "fmi3SetClock", nvr); }

static fmi3Status unsupported(fmi3Instance c, const char *f) {
    Instance *S = (Instance *)c;
    if (invalidState(S, f, ANY)) return fmi3Error;
    logError(S, "%s: not supported by this co-simulation FMU.", f);
    return fail(S);
}

/* ---------------------------------------------------------------- FMU state: the whole
 * controller state, the window's ring of block sums included (ivc_get_state) */

static size_t stateBytes(const Instance *S) { return sizeof(Head) + (S->ctl ? ivc_state_size(S->ctl) : 0); }

static void saveTo(Instance *S, unsigned char *buf) {
    Head h = S->d;
    h.csize = S->ctl ? ivc_state_size(S->ctl) : 0;
    memcpy(buf, &h, sizeof h);
    if (S->ctl) ivc_get_state(S->ctl, buf + sizeof h, h.csize);
}

static fmi3Status restoreFrom(Instance *S, const char *f, const unsigned char *buf, size_t size) {
    Head h;
    char msg[256];
    if (size < sizeof h) { logError(S, "%s: state of %lu bytes is too short.", f, (unsigned long)size); return fail(S); }
    memcpy(&h, buf, sizeof h);
    if (size != sizeof h + h.csize || (h.has_controller && h.csize == 0)) {
        logError(S, "%s: inconsistent state (%lu bytes).", f, (unsigned long)size);
        return fail(S);
    }
    if (h.has_controller) {
        if (!S->ctl || ivc_state_size(S->ctl) != h.csize) {
            ivc_free(S->ctl);
            S->ctl = ivc_init(h.par, msg, sizeof msg);
            if (!S->ctl) { logError(S, "%s: %s.", f, msg); return fail(S); }
        }
        if (ivc_set_state(S->ctl, buf + sizeof h, h.csize) != IVC_OK) { logError(S, "%s: %s.", f, ivc_message(S->ctl)); return fail(S); }
    } else { ivc_free(S->ctl); S->ctl = NULL; }
    S->d = h;
    return fmi3OK;
}

fmi3Status fmi3GetFMUState(fmi3Instance c, fmi3FMUState *FMUState) {
    Instance *S = (Instance *)c;
    size_t *blob;
    if (invalidState(S, "fmi3GetFMUState", ANY)) return fmi3Error;
    if (nullPointer(S, "fmi3GetFMUState", "FMUState", FMUState)) return fmi3Error;
    if (*FMUState) free(*FMUState);
    blob = (size_t *)malloc(sizeof(size_t) + stateBytes(S));   /* [size][Head][controller] */
    if (!blob) { logError(S, "fmi3GetFMUState: out of memory."); return fail(S); }
    blob[0] = stateBytes(S);
    saveTo(S, (unsigned char *)(blob + 1));
    *FMUState = blob;
    return fmi3OK;
}

fmi3Status fmi3SetFMUState(fmi3Instance c, fmi3FMUState FMUState) {
    Instance *S = (Instance *)c;
    const size_t *blob = (const size_t *)FMUState;
    if (invalidState(S, "fmi3SetFMUState", ANY)) return fmi3Error;
    if (nullPointer(S, "fmi3SetFMUState", "FMUState", FMUState)) return fmi3Error;
    return restoreFrom(S, "fmi3SetFMUState", (const unsigned char *)(blob + 1), blob[0]);
}

fmi3Status fmi3FreeFMUState(fmi3Instance c, fmi3FMUState *FMUState) {
    Instance *S = (Instance *)c;
    if (invalidState(S, "fmi3FreeFMUState", ANY)) return fmi3Error;
    if (nullPointer(S, "fmi3FreeFMUState", "FMUState", FMUState)) return fmi3Error;
    free(*FMUState);
    *FMUState = NULL;
    return fmi3OK;
}

fmi3Status fmi3SerializedFMUStateSize(fmi3Instance c, fmi3FMUState FMUState, size_t *size) {
    Instance *S = (Instance *)c;
    if (invalidState(S, "fmi3SerializedFMUStateSize", ANY)) return fmi3Error;
    if (nullPointer(S, "fmi3SerializedFMUStateSize", "FMUState", FMUState) ||
        nullPointer(S, "fmi3SerializedFMUStateSize", "size", size)) return fmi3Error;
    *size = ((const size_t *)FMUState)[0];
    return fmi3OK;
}

fmi3Status fmi3SerializeFMUState(fmi3Instance c, fmi3FMUState FMUState, fmi3Byte serializedState[], size_t size) {
    Instance *S = (Instance *)c;
    const size_t *blob = (const size_t *)FMUState;
    if (invalidState(S, "fmi3SerializeFMUState", ANY)) return fmi3Error;
    if (nullPointer(S, "fmi3SerializeFMUState", "FMUState", FMUState) ||
        nullPointer(S, "fmi3SerializeFMUState", "serializedState", serializedState)) return fmi3Error;
    if (size != blob[0]) {
        logError(S, "fmi3SerializeFMUState: buffer of %lu bytes, the state has %lu.", (unsigned long)size, (unsigned long)blob[0]);
        return fail(S);
    }
    memcpy(serializedState, blob + 1, size);
    return fmi3OK;
}

fmi3Status fmi3DeserializeFMUState(fmi3Instance c, const fmi3Byte serializedState[], size_t size, fmi3FMUState *FMUState) {
    Instance *S = (Instance *)c;
    size_t *blob;
    Head h;
    if (invalidState(S, "fmi3DeserializeFMUState", ANY)) return fmi3Error;
    if (nullPointer(S, "fmi3DeserializeFMUState", "serializedState", serializedState) ||
        nullPointer(S, "fmi3DeserializeFMUState", "FMUState", FMUState)) return fmi3Error;
    if (size < sizeof h) { logError(S, "fmi3DeserializeFMUState: %lu bytes is too short.", (unsigned long)size); return fail(S); }
    memcpy(&h, serializedState, sizeof h);
    if (size != sizeof h + h.csize) { logError(S, "fmi3DeserializeFMUState: %lu bytes, the state says %lu.", (unsigned long)size, (unsigned long)(sizeof h + h.csize)); return fail(S); }
    blob = (size_t *)malloc(sizeof(size_t) + size);
    if (!blob) { logError(S, "fmi3DeserializeFMUState: out of memory."); return fail(S); }
    blob[0] = size;
    memcpy(blob + 1, serializedState, size);
    if (*FMUState) free(*FMUState);
    *FMUState = blob;
    return fmi3OK;
}

/* ---------------------------------------------------------------- co-simulation */

fmi3Status fmi3DoStep(fmi3Instance c, fmi3Float64 currentCommunicationPoint, fmi3Float64 communicationStepSize,
                      fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean *eventHandlingNeeded,
                      fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime) {
    Instance *S = (Instance *)c;
    double tau[IVC_NQ], h;
    int st;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (invalidState(S, "fmi3DoStep", StepMode)) return fmi3Error;
    if (eventHandlingNeeded) *eventHandlingNeeded = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (earlyReturn) *earlyReturn = fmi3False;
    if (lastSuccessfulTime) *lastSuccessfulTime = S->d.time;
    h = S->d.par[IVC_P_H];
    if (!(fabs(communicationStepSize - h) <= 1e-9 * h)) {
        logError(S, "fmi3DoStep: communication step %g must equal the controller's sample period h = %g.", communicationStepSize, h);
        return fail(S);
    }
    if (!(fabs(currentCommunicationPoint - S->d.time) <= 1e-9 * (S->d.time > 1 ? S->d.time : 1))) {
        logError(S, "fmi3DoStep: communication point %.17g, but the FMU is at t = %.17g.", currentCommunicationPoint, S->d.time);
        return fail(S);
    }
    st = ivc_step(S->ctl, ivc_time(S->ctl), S->d.in, S->d.in + IVC_NQ, tau);
    if (st != IVC_OK) {
        logError(S, "fmi3DoStep at t = %g: %s.", currentCommunicationPoint, ivc_message(S->ctl));
        return fail(S);
    }
    S->d.time = ivc_time(S->ctl);
    if (lastSuccessfulTime) *lastSuccessfulTime = S->d.time;
    return fmi3OK;
}

/* ---------------------------------------------------------------- not supported */
fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference, size_t* nDependencies) { (void)valueReference; (void)nDependencies; return unsupported(instance, "fmi3GetNumberOfVariableDependencies"); }
fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent, size_t elementIndicesOfDependent[], fmi3ValueReference independents[], size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[], size_t nDependencies) { (void)dependent; (void)elementIndicesOfDependent; (void)independents; (void)elementIndicesOfIndependents; (void)dependencyKinds; (void)nDependencies; return unsupported(instance, "fmi3GetVariableDependencies"); }
fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns, const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) { (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed; (void)sensitivity; (void)nSensitivity; return unsupported(instance, "fmi3GetDirectionalDerivative"); }
fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns, const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) { (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed; (void)sensitivity; (void)nSensitivity; return unsupported(instance, "fmi3GetAdjointDerivative"); }
fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) {  return unsupported(instance, "fmi3EnterConfigurationMode"); }
fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) {  return unsupported(instance, "fmi3ExitConfigurationMode"); }
fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[]) { (void)valueReferences; (void)nValueReferences; (void)intervals; (void)qualifiers; return unsupported(instance, "fmi3GetIntervalDecimal"); }
fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[], fmi3IntervalQualifier qualifiers[]) { (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions; (void)qualifiers; return unsupported(instance, "fmi3GetIntervalFraction"); }
fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float64 shifts[]) { (void)valueReferences; (void)nValueReferences; (void)shifts; return unsupported(instance, "fmi3GetShiftDecimal"); }
fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[]) { (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions; return unsupported(instance, "fmi3GetShiftFraction"); }
fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float64 intervals[]) { (void)valueReferences; (void)nValueReferences; (void)intervals; return unsupported(instance, "fmi3SetIntervalDecimal"); }
fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) { (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions; return unsupported(instance, "fmi3SetIntervalFraction"); }
fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float64 shifts[]) { (void)valueReferences; (void)nValueReferences; (void)shifts; return unsupported(instance, "fmi3SetShiftDecimal"); }
fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) { (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions; return unsupported(instance, "fmi3SetShiftFraction"); }
fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) {  return unsupported(instance, "fmi3EvaluateDiscreteStates"); }
fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean* discreteStatesNeedUpdate, fmi3Boolean* terminateSimulation, fmi3Boolean* nominalsOfContinuousStatesChanged, fmi3Boolean* valuesOfContinuousStatesChanged, fmi3Boolean* nextEventTimeDefined, fmi3Float64* nextEventTime) { (void)discreteStatesNeedUpdate; (void)terminateSimulation; (void)nominalsOfContinuousStatesChanged; (void)valuesOfContinuousStatesChanged; (void)nextEventTimeDefined; (void)nextEventTime; return unsupported(instance, "fmi3UpdateDiscreteStates"); }
fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance) {  return unsupported(instance, "fmi3EnterContinuousTimeMode"); }
fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean* enterEventMode, fmi3Boolean* terminateSimulation) { (void)noSetFMUStatePriorToCurrentPoint; (void)enterEventMode; (void)terminateSimulation; return unsupported(instance, "fmi3CompletedIntegratorStep"); }
fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time) { (void)time; return unsupported(instance, "fmi3SetTime"); }
fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 continuousStates[], size_t nContinuousStates) { (void)continuousStates; (void)nContinuousStates; return unsupported(instance, "fmi3SetContinuousStates"); }
fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 derivatives[], size_t nContinuousStates) { (void)derivatives; (void)nContinuousStates; return unsupported(instance, "fmi3GetContinuousStateDerivatives"); }
fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 eventIndicators[], size_t nEventIndicators) { (void)eventIndicators; (void)nEventIndicators; return unsupported(instance, "fmi3GetEventIndicators"); }
fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 continuousStates[], size_t nContinuousStates) { (void)continuousStates; (void)nContinuousStates; return unsupported(instance, "fmi3GetContinuousStates"); }
fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[], size_t nContinuousStates) { (void)nominals; (void)nContinuousStates; return unsupported(instance, "fmi3GetNominalsOfContinuousStates"); }
fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t* nEventIndicators) { (void)nEventIndicators; return unsupported(instance, "fmi3GetNumberOfEventIndicators"); }
fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t* nContinuousStates) { (void)nContinuousStates; return unsupported(instance, "fmi3GetNumberOfContinuousStates"); }
fmi3Status fmi3EnterEventMode(fmi3Instance instance) {  return unsupported(instance, "fmi3EnterEventMode"); }
fmi3Status fmi3EnterStepMode(fmi3Instance instance) {  return unsupported(instance, "fmi3EnterStepMode"); }
fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int32 orders[], fmi3Float64 values[], size_t nValues) { (void)valueReferences; (void)nValueReferences; (void)orders; (void)values; (void)nValues; return unsupported(instance, "fmi3GetOutputDerivatives"); }
fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference, fmi3Float64 activationTime) { (void)clockReference; (void)activationTime; return unsupported(instance, "fmi3ActivateModelPartition"); }
