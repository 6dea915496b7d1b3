/* fmi2_controller.c: FMI 2.0 co-simulation wrapper of the sampled controller library
 * (ivdrem_controller.c), shipped unchanged in every controller FMU that ivdrem exports
 * (ivdrem/controller/fmu_export.py); sizes, value references and names come from the
 * generated controller_fmu.h.
 *
 * Structure and state machine follow the FMI Reference FMUs, as fmi2_plant.c does: every
 * function checks the state it is called in, and an illegal call or a bad value is logged
 * (category logStatusError) and returns fmi2Error, never crashes.
 *
 * Timing (docs/controller.md, "Where the torque goes"): fmi2DoStep(t_k, h) reads the
 * inputs q(t_k), dq(t_k) and computes tau_k, which is the output from then on (the torque
 * for [t_k+1, t_k+2]): delay 1, no direct feedthrough, so every Jacobi host computes the
 * same loop.  The communication step must equal the controller's sample period h.
 * Before the first step the torque output is 0.
 *
 * fmi2GetFMUstate copies the whole controller state, the window's ring of block sums
 * included (ivc_get_state); a restored FMU continues bit for bit.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "ivdrem_controller.h"
#include "controller_fmu.h"

typedef enum {
    StartAndEnd = 1 << 0, Instantiated = 1 << 1, InitializationMode = 1 << 2,
    StepComplete = 1 << 5, StepInProgress = 1 << 6, StepFailed = 1 << 7,
    StepCanceled = 1 << 8, Terminated = 1 << 9, Error = 1 << 10, Fatal = 1 << 11
} ModelState;

#define MASK_AnyButStart (Instantiated | InitializationMode | StepComplete | StepFailed | \
                          StepCanceled | Terminated | Error)
#define MASK_fmi2FreeInstance            MASK_AnyButStart
#define MASK_fmi2SetDebugLogging         MASK_AnyButStart
#define MASK_fmi2SetupExperiment         Instantiated
#define MASK_fmi2EnterInitializationMode Instantiated
#define MASK_fmi2ExitInitializationMode  InitializationMode
#define MASK_fmi2Terminate               (StepComplete | StepFailed)
#define MASK_fmi2Reset                   MASK_AnyButStart
#define MASK_fmi2GetReal                 (InitializationMode | StepComplete | StepFailed | \
                                          StepCanceled | Terminated | Error)
#define MASK_fmi2SetReal                 (Instantiated | InitializationMode | StepComplete)
#define MASK_fmi2FMUstate                MASK_AnyButStart
#define MASK_fmi2DoStep                  StepComplete
#define MASK_fmi2GetStatus               (StepComplete | StepInProgress | StepFailed | Terminated)

#define INSTANCE_MAGIC 0x1D4E3C7Bu

/* what an FMU state saves besides the controller's own state */
typedef struct {
    int state;
    int has_controller;
    double time;
    double in[2 * IVC_NQ];
    double par[IVC_NPAR];
    size_t csize;                       /* bytes of the controller state that follow */
} Head;

typedef struct {
    unsigned int magic;
    Head d;
    ivc_controller *ctl;                /* created by fmi2ExitInitializationMode */
    char *instanceName;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    int logEvents;
} Instance;

static void logMessage(Instance *S, fmi2Status status, const char *category, const char *fmt, ...) {
    char buf[1024], msg[2048];
    size_t i, j;
    va_list args;
    if (!S || !S->logger) return;
    if (status == fmi2OK && !S->logEvents) return;
    va_start(args, fmt);
    vsnprintf(buf, sizeof(buf), fmt, args);
    va_end(args);
    for (i = 0, j = 0; buf[i] && j + 2 < sizeof(msg); i++) {
        if (buf[i] == '%') msg[j++] = '%';
        msg[j++] = buf[i];
    }
    msg[j] = '\0';
    S->logger(S->env, S->instanceName, status, category, msg);
}

#define logError(S, ...) logMessage(S, fmi2Error, "logStatusError", __VA_ARGS__)

static int invalidState(Instance *S, const char *f, int mask) {
    if (!S || S->magic != INSTANCE_MAGIC) return 1;
    if (!(S->d.state & mask)) {
        logError(S, "%s: illegal call sequence (not allowed in the current state).", f);
        S->d.state = Error;
        return 1;
    }
    return 0;
}

static int nullPointer(Instance *S, const char *f, const char *arg, const void *p) {
    if (p) return 0;
    logError(S, "%s: invalid argument %s = NULL.", f, arg);
    S->d.state = Error;
    return 1;
}

static fmi2Status fail(Instance *S) {
    S->d.state = Error;
    return fmi2Error;
}

#define CHECK_STATE(f) \
    if (invalidState(S, #f, MASK_##f)) return fmi2Error;

static void vrName(fmi2ValueReference vr, char *buf, size_t n) {
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

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    Instance tmp, *S;
    (void)fmuResourceLocation;
    (void)visible;
    memset(&tmp, 0, sizeof(tmp));
    tmp.instanceName = (char *)(instanceName ? instanceName : "?");
    if (functions) {
        tmp.logger = functions->logger;
        tmp.env = functions->componentEnvironment;
    }
    if (!instanceName || !instanceName[0]) {
        logError(&tmp, "fmi2Instantiate: missing instance name.");
        return NULL;
    }
    if (fmuType != fmi2CoSimulation) {
        logError(&tmp, "fmi2Instantiate: the controller is a co-simulation FMU only (fmuType %d).", (int)fmuType);
        return NULL;
    }
    if (!fmuGUID || strcmp(fmuGUID, MODEL_GUID) != 0) {
        logError(&tmp, "fmi2Instantiate: wrong GUID %s, expected %s.", fmuGUID ? fmuGUID : "NULL", MODEL_GUID);
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

void fmi2FreeInstance(fmi2Component c) {
    Instance *S = (Instance *)c;
    if (!S) return;
    if (invalidState(S, "fmi2FreeInstance", MASK_fmi2FreeInstance)) return;
    S->magic = 0;
    ivc_free(S->ctl);
    free(S->instanceName);
    free(S);
}

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    Instance *S = (Instance *)c;
    size_t i;
    CHECK_STATE(fmi2SetDebugLogging)
    if (nCategories > 0 && nullPointer(S, "fmi2SetDebugLogging", "categories", categories)) return fmi2Error;
    for (i = 0; i < nCategories; i++) {
        if (!categories[i] || (strcmp(categories[i], "logEvents") != 0 &&
                               strcmp(categories[i], "logStatusError") != 0)) {
            logError(S, "fmi2SetDebugLogging: unknown log category %s.", categories[i] ? categories[i] : "NULL");
            return fail(S);
        }
    }
    S->logEvents = loggingOn ? 1 : 0;
    return fmi2OK;
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    Instance *S = (Instance *)c;
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTime;
    (void)stopTimeDefined;
    CHECK_STATE(fmi2SetupExperiment)
    if (startTime != 0.0) {
        logError(S, "fmi2SetupExperiment: the controller starts at t = 0 (its mu(t), F(t) and "
                    "reference are functions of t), got start time %g.", startTime);
        return fail(S);
    }
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2EnterInitializationMode)
    S->d.state = InitializationMode;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *S = (Instance *)c;
    char msg[256];
    CHECK_STATE(fmi2ExitInitializationMode)
    ivc_free(S->ctl);
    S->ctl = ivc_init(S->d.par, msg, sizeof msg);        /* the only allocation */
    if (!S->ctl) {
        logError(S, "fmi2ExitInitializationMode: %s.", msg);
        return fail(S);
    }
    S->d.has_controller = 1;
    S->d.time = 0.0;
    S->d.state = StepComplete;
    logMessage(S, fmi2OK, "logEvents", "fmi2ExitInitializationMode: window of %lu bytes.",
               (unsigned long)ivc_window_bytes(S->ctl));
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2Terminate)
    S->d.state = Terminated;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2Reset)
    ivc_free(S->ctl);
    S->ctl = NULL;
    S->d.has_controller = 0;
    setStartValues(S);
    S->d.state = Instantiated;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    Instance *S = (Instance *)c;
    double th[IVC_NTHETA], tdh[IVC_NQ], D = 0.0, tau[IVC_NQ];
    size_t i;
    CHECK_STATE(fmi2GetReal)
    if (nvr > 0 && (nullPointer(S, "fmi2GetReal", "vr[]", vr) ||
                    nullPointer(S, "fmi2GetReal", "value[]", value))) return fmi2Error;
    if (S->ctl) ivc_outputs(S->ctl, th, tdh, &D, tau);
    else {
        for (i = 0; i < IVC_NTHETA; i++) th[i] = S->d.par[IVC_P_THETA_HAT0 + i];
        for (i = 0; i < IVC_NQ; i++) tdh[i] = tau[i] = 0.0;
    }
    for (i = 0; i < nvr; i++) {
        fmi2ValueReference r = vr[i];
        if (r < VR_TAU) value[i] = S->d.in[r];
        else if (r < VR_THETA_HAT) value[i] = tau[r - VR_TAU];
        else if (r < VR_TAU_D_HAT) value[i] = th[r - VR_THETA_HAT];
        else if (r < VR_DELTA) value[i] = tdh[r - VR_TAU_D_HAT];
        else if (r == VR_DELTA) value[i] = D;
        else if (r < VR_PAR + IVC_NPAR) value[i] = S->ctl ? ivc_get_param(S->ctl, (int)(r - VR_PAR)) : S->d.par[r - VR_PAR];
        else {
            logError(S, "fmi2GetReal: unknown value reference %u.", r);
            return fail(S);
        }
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    Instance *S = (Instance *)c;
    char name[64];
    size_t i;
    CHECK_STATE(fmi2SetReal)
    if (nvr > 0 && (nullPointer(S, "fmi2SetReal", "vr[]", vr) ||
                    nullPointer(S, "fmi2SetReal", "value[]", value))) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        fmi2ValueReference r = vr[i];
        vrName(r, name, sizeof name);
        if (r < VR_TAU) {
            if (!isfinite(value[i])) {
                logError(S, "fmi2SetReal: %s = %g is not finite.", name, value[i]);
                return fail(S);
            }
            S->d.in[r] = value[i];
        } else if (r >= VR_PAR && r < VR_PAR + IVC_NPAR) {
            int k = (int)(r - VR_PAR);
            if (!PARAMETER_EXPOSED[k]) {
                logError(S, "fmi2SetReal: %s is fixed in this FMU.", name);
                return fail(S);
            }
            if (S->d.state == StepComplete) {
                if (!PARAMETER_TUNABLE[k]) {
                    logError(S, "fmi2SetReal: parameter %s is fixed after initialization.", name);
                    return fail(S);
                }
                if (ivc_set_param(S->ctl, k, value[i]) != IVC_OK) {
                    logError(S, "fmi2SetReal: %s = %g refused: %s.", name, value[i], ivc_message(S->ctl));
                    return fail(S);
                }
            }
            if (isnan(value[i])) {
                logError(S, "fmi2SetReal: %s is NaN.", name);
                return fail(S);
            }
            S->d.par[k] = value[i];
        } else {
            logError(S, "fmi2SetReal: %s cannot be set (an output or unknown).", name);
            return fail(S);
        }
    }
    return fmi2OK;
}

static fmi2Status noSuchVariables(Instance *S, const char *f, size_t nvr) {
    if (nvr == 0) return fmi2OK;
    logError(S, "%s: the FMU has no variables of this type.", f);
    return fail(S);
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    Instance *S = (Instance *)c; (void)vr; (void)value; CHECK_STATE(fmi2GetReal) return noSuchVariables(S, "fmi2GetInteger", nvr);
}
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    Instance *S = (Instance *)c; (void)vr; (void)value; CHECK_STATE(fmi2GetReal) return noSuchVariables(S, "fmi2GetBoolean", nvr);
}
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    Instance *S = (Instance *)c; (void)vr; (void)value; CHECK_STATE(fmi2GetReal) return noSuchVariables(S, "fmi2GetString", nvr);
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    Instance *S = (Instance *)c; (void)vr; (void)value; CHECK_STATE(fmi2SetReal) return noSuchVariables(S, "fmi2SetInteger", nvr);
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[]) {
    Instance *S = (Instance *)c; (void)vr; (void)value; CHECK_STATE(fmi2SetReal) return noSuchVariables(S, "fmi2SetBoolean", nvr);
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    Instance *S = (Instance *)c; (void)vr; (void)value; CHECK_STATE(fmi2SetReal) return noSuchVariables(S, "fmi2SetString", nvr);
}

/* ---------------------------------------------------------------- FMU state */

static size_t stateBytes(const Instance *S) {
    return sizeof(Head) + (S->ctl ? ivc_state_size(S->ctl) : 0);
}

static void saveTo(Instance *S, unsigned char *buf) {
    Head h = S->d;
    h.csize = S->ctl ? ivc_state_size(S->ctl) : 0;
    memcpy(buf, &h, sizeof h);
    if (S->ctl) ivc_get_state(S->ctl, buf + sizeof h, h.csize);
}

static fmi2Status restoreFrom(Instance *S, const char *f, const unsigned char *buf, size_t size) {
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
        if (ivc_set_state(S->ctl, buf + sizeof h, h.csize) != IVC_OK) {
            logError(S, "%s: %s.", f, ivc_message(S->ctl));
            return fail(S);
        }
    } else {
        ivc_free(S->ctl);
        S->ctl = NULL;
    }
    S->d = h;
    return fmi2OK;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *S = (Instance *)c;
    size_t *blob;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2GetFMUstate", "FMUstate", FMUstate)) return fmi2Error;
    if (*FMUstate) free(*FMUstate);
    blob = (size_t *)malloc(sizeof(size_t) + stateBytes(S));   /* [size][Head][controller] */
    if (!blob) { logError(S, "fmi2GetFMUstate: out of memory."); return fail(S); }
    blob[0] = stateBytes(S);
    saveTo(S, (unsigned char *)(blob + 1));
    *FMUstate = blob;
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    Instance *S = (Instance *)c;
    const size_t *blob = (const size_t *)FMUstate;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2SetFMUstate", "FMUstate", FMUstate)) return fmi2Error;
    return restoreFrom(S, "fmi2SetFMUstate", (const unsigned char *)(blob + 1), blob[0]);
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2FreeFMUstate", "FMUstate", FMUstate)) return fmi2Error;
    free(*FMUstate);
    *FMUstate = NULL;
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2SerializedFMUstateSize", "FMUstate", FMUstate) ||
        nullPointer(S, "fmi2SerializedFMUstateSize", "size", size)) return fmi2Error;
    *size = ((const size_t *)FMUstate)[0];
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[], size_t size) {
    Instance *S = (Instance *)c;
    const size_t *blob = (const size_t *)FMUstate;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2SerializeFMUstate", "FMUstate", FMUstate) ||
        nullPointer(S, "fmi2SerializeFMUstate", "serializedState", serializedState)) return fmi2Error;
    if (size != blob[0]) {
        logError(S, "fmi2SerializeFMUstate: buffer of %lu bytes, the state has %lu.",
                 (unsigned long)size, (unsigned long)blob[0]);
        return fail(S);
    }
    memcpy(serializedState, blob + 1, size);
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    Instance *S = (Instance *)c;
    size_t *blob;
    Head h;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2DeSerializeFMUstate", "serializedState", serializedState) ||
        nullPointer(S, "fmi2DeSerializeFMUstate", "FMUstate", FMUstate)) return fmi2Error;
    if (size < sizeof h) { logError(S, "fmi2DeSerializeFMUstate: %lu bytes is too short.", (unsigned long)size); return fail(S); }
    memcpy(&h, serializedState, sizeof h);
    if (size != sizeof h + h.csize) {
        logError(S, "fmi2DeSerializeFMUstate: %lu bytes, the state says %lu.", (unsigned long)size,
                 (unsigned long)(sizeof h + h.csize));
        return fail(S);
    }
    blob = (size_t *)malloc(sizeof(size_t) + size);
    if (!blob) { logError(S, "fmi2DeSerializeFMUstate: out of memory."); return fail(S); }
    blob[0] = size;
    memcpy(blob + 1, serializedState, size);
    if (*FMUstate) free(*FMUstate);
    *FMUstate = blob;
    return fmi2OK;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[], size_t nUnknown,
                                        const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[]) {
    Instance *S = (Instance *)c;
    (void)vUnknown_ref; (void)nUnknown; (void)vKnown_ref; (void)nKnown; (void)dvKnown; (void)dvUnknown;
    if (invalidState(S, "fmi2GetDirectionalDerivative", MASK_AnyButStart)) return fmi2Error;
    logError(S, "fmi2GetDirectionalDerivative: not provided (providesDirectionalDerivative=\"false\").");
    return fail(S);
}

/* ---------------------------------------------------------------- co-simulation */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    Instance *S = (Instance *)c;
    (void)vr; (void)nvr; (void)order; (void)value;
    if (invalidState(S, "fmi2SetRealInputDerivatives", MASK_AnyButStart)) return fmi2Error;
    logError(S, "fmi2SetRealInputDerivatives: canInterpolateInputs=\"false\".");
    return fail(S);
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    Instance *S = (Instance *)c;
    (void)vr; (void)nvr; (void)order; (void)value;
    if (invalidState(S, "fmi2GetRealOutputDerivatives", MASK_AnyButStart)) return fmi2Error;
    logError(S, "fmi2GetRealOutputDerivatives: maxOutputDerivativeOrder=\"0\".");
    return fail(S);
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    Instance *S = (Instance *)c;
    double tau[IVC_NQ], h;
    int st;
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK_STATE(fmi2DoStep)
    h = S->d.par[IVC_P_H];
    if (!(fabs(communicationStepSize - h) <= 1e-9 * h)) {
        logError(S, "fmi2DoStep: communication step %g must equal the controller's sample period h = %g.",
                 communicationStepSize, h);
        return fail(S);
    }
    if (!(fabs(currentCommunicationPoint - S->d.time) <= 1e-9 * (S->d.time > 1 ? S->d.time : 1))) {
        logError(S, "fmi2DoStep: communication point %.17g, but the FMU is at t = %.17g.",
                 currentCommunicationPoint, S->d.time);
        return fail(S);
    }
    st = ivc_step(S->ctl, ivc_time(S->ctl), S->d.in, S->d.in + IVC_NQ, tau);
    if (st != IVC_OK) {
        logError(S, "fmi2DoStep at t = %g: %s.", currentCommunicationPoint, ivc_message(S->ctl));
        return fail(S);
    }
    S->d.time = ivc_time(S->ctl);
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    Instance *S = (Instance *)c;
    if (invalidState(S, "fmi2CancelStep", MASK_AnyButStart)) return fmi2Error;
    logError(S, "fmi2CancelStep: fmi2DoStep is synchronous; there is no step to cancel.");
    return fail(S);
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2GetStatus)
    if (nullPointer(S, "fmi2GetStatus", "value", value)) return fmi2Error;
    if (s == fmi2DoStepStatus) { *value = fmi2OK; return fmi2OK; }
    logError(S, "fmi2GetStatus: status kind %d is not provided.", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2GetStatus)
    if (nullPointer(S, "fmi2GetRealStatus", "value", value)) return fmi2Error;
    if (s == fmi2LastSuccessfulTime) { *value = S->d.time; return fmi2OK; }
    logError(S, "fmi2GetRealStatus: status kind %d is not provided.", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    Instance *S = (Instance *)c;
    (void)value;
    CHECK_STATE(fmi2GetStatus)
    logError(S, "fmi2GetIntegerStatus: status kind %d is not provided.", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2GetStatus)
    if (nullPointer(S, "fmi2GetBooleanStatus", "value", value)) return fmi2Error;
    if (s == fmi2Terminated) { *value = fmi2False; return fmi2OK; }
    logError(S, "fmi2GetBooleanStatus: status kind %d is not provided.", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    Instance *S = (Instance *)c;
    (void)value;
    CHECK_STATE(fmi2GetStatus)
    logError(S, "fmi2GetStringStatus: status kind %d is not provided.", (int)s);
    return fmi2Discard;
}
