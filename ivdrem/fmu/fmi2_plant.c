/* fmi2_plant.c: FMI 2.0 model exchange + co-simulation for an Euler-Lagrange plant
 *
 *     M(q) q'' + C(q,q') q' + F(q') + G(q) = tau + tau_d
 *
 * Shipped unchanged in every FMU exported by ivdrem (ivdrem/fmu/export.py); all model
 * specific parts (sizes, value references, start values, the model's C face with its
 * forward dynamics) come from the generated plant_model.h / plant_model.c.
 *
 * Structure and state machine follow the FMI Reference FMUs
 * (github.com/modelica/Reference-FMUs, src/fmi2Functions.c): every function checks that it
 * is called in an allowed state, and an illegal call or a bad value is logged and returns
 * fmi2Error (the instance then enters the Error state, FMI 2.0.4 section 2.1.3), never
 * crashes. State machine: FMI 2.0.4 figures 6 (model exchange) and 7 (co-simulation).
 *
 * Dynamics: q'' = M(q)^-1 (tau + tau_d - b), by the model's C face (plant_model.c), whose
 * Cholesky factorisation also checks that M(q) is positive definite by the package's one
 * rule (parameters that make M singular or indefinite give fmi2Error with a message).
 *
 * Co-simulation: fmi2DoStep integrates over [t, t+H] with k = ceil(H/h) fixed-step
 * classical Runge-Kutta (RK4) sub-steps of equal size H/k <= h, where h is the parameter
 * "cs_substep". Inputs are held constant over the communication step (zero-order hold;
 * canInterpolateInputs="false").
 *
 * Needs nothing but libc and libm. Memory: calloc/free (canNotUseMemoryManagementFunctions).
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "plant_model.h"

#define NX (2 * NQ) /* continuous states x = [q, q'] */

/* states of the state machine, as in the Reference FMUs */
typedef enum {
    StartAndEnd        = 1 << 0,
    Instantiated       = 1 << 1,
    InitializationMode = 1 << 2,
    EventMode          = 1 << 3, /* model exchange */
    ContinuousTimeMode = 1 << 4, /* model exchange */
    StepComplete       = 1 << 5, /* co-simulation */
    StepInProgress     = 1 << 6, /* co-simulation */
    StepFailed         = 1 << 7, /* co-simulation */
    StepCanceled       = 1 << 8, /* co-simulation */
    Terminated         = 1 << 9,
    Error              = 1 << 10,
    Fatal              = 1 << 11
} ModelState;

/* allowed states per function (Reference FMUs, fmi2Functions.c) */
#define MASK_AnyButStart (Instantiated | InitializationMode | EventMode | ContinuousTimeMode | \
                          StepComplete | StepFailed | StepCanceled | Terminated | Error)
#define MASK_fmi2FreeInstance            MASK_AnyButStart
#define MASK_fmi2SetDebugLogging         MASK_AnyButStart
#define MASK_fmi2SetupExperiment         Instantiated
#define MASK_fmi2EnterInitializationMode Instantiated
#define MASK_fmi2ExitInitializationMode  InitializationMode
#define MASK_fmi2Terminate               (EventMode | ContinuousTimeMode | StepComplete | StepFailed)
#define MASK_fmi2Reset                   MASK_AnyButStart
#define MASK_fmi2GetReal                 (InitializationMode | EventMode | ContinuousTimeMode | \
                                          StepComplete | StepFailed | StepCanceled | Terminated | Error)
#define MASK_fmi2SetReal                 (Instantiated | InitializationMode | EventMode | \
                                          ContinuousTimeMode | StepComplete)
#define MASK_fmi2FMUstate                MASK_AnyButStart
#define MASK_fmi2EnterEventMode          (EventMode | ContinuousTimeMode)
#define MASK_fmi2NewDiscreteStates       EventMode
#define MASK_fmi2EnterContinuousTimeMode EventMode
#define MASK_fmi2CompletedIntegratorStep ContinuousTimeMode
#define MASK_fmi2SetTime                 (EventMode | ContinuousTimeMode)
#define MASK_fmi2SetContinuousStates     ContinuousTimeMode
#define MASK_fmi2GetEventIndicators      (InitializationMode | EventMode | ContinuousTimeMode | Terminated | Error)
#define MASK_fmi2GetContinuousStates     MASK_fmi2GetEventIndicators
#define MASK_fmi2GetDerivatives          (EventMode | ContinuousTimeMode | Terminated | Error)
#define MASK_fmi2GetNominals             (Instantiated | EventMode | ContinuousTimeMode | Terminated | Error)
#define MASK_fmi2DoStep                  StepComplete
#define MASK_fmi2GetStatus               (StepComplete | StepInProgress | StepFailed | Terminated)

/* everything that an FMU state (fmi2GetFMUstate) has to save */
typedef struct {
    int    type;           /* fmi2ModelExchange or fmi2CoSimulation */
    int    state;          /* ModelState */
    double time;
    double x[NX];          /* q, q' */
    double u[2 * NQ];      /* tau, tau_d */
    double p[NP];          /* theta, then the model constants (e.g. g) */
    double h;              /* co-simulation RK4 sub-step bound, "cs_substep" */
} Data;

/* Set by fmi2Instantiate, cleared by fmi2FreeInstance: a second fmi2FreeInstance (or any
 * call) on a freed instance is undefined in FMI 2.0, but returning instead of freeing twice
 * costs one comparison.  First member, so that it is the word the allocator reuses. */
#define INSTANCE_MAGIC 0x1D4E3A7Bu

typedef struct {
    unsigned int magic;    /* INSTANCE_MAGIC while the instance is alive */
    Data d;
    char *instanceName;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    int logEvents;         /* debug category "logEvents" */
} Instance;

/* ---------------------------------------------------------------- logging */

static void logMessage(Instance *S, fmi2Status status, const char *category, const char *fmt, ...) {
    char buf[1024], msg[2048];
    size_t i, j;
    va_list args;
    if (!S || !S->logger) return;
    if (status == fmi2OK && !S->logEvents) return; /* errors are always reported */
    va_start(args, fmt);
    vsnprintf(buf, sizeof(buf), fmt, args);
    va_end(args);
    /* The message is complete text, with '%' doubled because the logger may treat it as a
       printf format.  No variadic arguments: importers whose logger cannot read them (a
       ctypes callback, say) still get the whole message. */
    for (i = 0, j = 0; buf[i] && j + 2 < sizeof(msg); i++) {
        if (buf[i] == '%') msg[j++] = '%';
        msg[j++] = buf[i];
    }
    msg[j] = '\0';
    S->logger(S->env, S->instanceName, status, category, msg);
}

#define logError(S, ...) logMessage(S, fmi2Error, "logStatusError", __VA_ARGS__)

/* checks at the start of each function (Reference FMUs: BEGIN_FUNCTION / allowedState) */
static int invalidState(Instance *S, const char *f, int mask) {
    if (!S || S->magic != INSTANCE_MAGIC) return 1; /* NULL or already freed: no logger left */
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

/* name of a value reference, for messages (layout: see plant_model.h) */
static void vrName(fmi2ValueReference vr, char *buf, size_t n) {
    if (vr < VR_DQ)             snprintf(buf, n, "q[%u]", vr - VR_Q);
    else if (vr < VR_DER_Q)     snprintf(buf, n, "dq[%u]", vr - VR_DQ);
    else if (vr < VR_DER_DQ)    snprintf(buf, n, "der(q[%u])", vr - VR_DER_Q);
    else if (vr < VR_TAU)       snprintf(buf, n, "der(dq[%u])", vr - VR_DER_DQ);
    else if (vr < VR_TAU_D)     snprintf(buf, n, "tau[%u]", vr - VR_TAU);
    else if (vr < VR_P)         snprintf(buf, n, "tau_d[%u]", vr - VR_TAU_D);
    else if (vr < VR_SUBSTEP)   snprintf(buf, n, "%s", PARAMETER_NAMES[vr - VR_P]);
    else if (vr == VR_SUBSTEP)  snprintf(buf, n, "cs_substep");
    else                        snprintf(buf, n, "#%u", vr);
}

/* ---------------------------------------------------------------- dynamics */

/* q'' = M(q)^-1 (tau + tau_d - b(q, q')) by the model's C face (forward_dynamics_k: a
 * Cholesky with the package's one rule for "positive definite", docs/models.md).
 * Returns 0 on success, 1 if M is not positive definite, 2 if a result is not finite. */
static int accelerations(const double *p, const double *x, const double *u, double *ddq) {
    double tau[NQ];
    int i;
    for (i = 0; i < NQ; i++) tau[i] = u[i] + u[NQ + i]; /* tau + tau_d */
    if (plant_accelerations(x, x + NQ, tau, p, ddq) != 0) return 1;
    for (i = 0; i < NQ; i++)
        if (!isfinite(ddq[i])) return 2;
    return 0;
}

/* x' = f(x) = [q', q''], logging why it fails */
static int stateDerivatives(Instance *S, const double *x, double *dx) {
    int i, rc;
    rc = accelerations(S->d.p, x, S->d.u, dx + NQ);
    if (rc == 1) {
        logError(S, "M(q) is singular or not positive definite at t = %g (q[0] = %g): check the "
                    "parameters theta and the state.", S->d.time, x[0]);
        return 1;
    }
    if (rc == 2) {
        logError(S, "the accelerations are not finite at t = %g.", S->d.time);
        return 1;
    }
    for (i = 0; i < NQ; i++) dx[i] = x[NQ + i];
    return 0;
}

/* ---------------------------------------------------------------- instance life cycle */

static void setStartValues(Instance *S) {
    int i;
    S->d.time = 0;
    for (i = 0; i < NQ; i++) {
        S->d.x[i] = Q_START[i];
        S->d.x[NQ + i] = DQ_START[i];
        S->d.u[i] = 0;
        S->d.u[NQ + i] = 0;
    }
    for (i = 0; i < NP; i++) S->d.p[i] = P_START[i];
    S->d.h = SUBSTEP_START;
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
    if (fmuType != fmi2ModelExchange && fmuType != fmi2CoSimulation) {
        logError(&tmp, "fmi2Instantiate: unknown fmuType %d.", (int)fmuType);
        return NULL;
    }
    if (!fmuGUID || strcmp(fmuGUID, MODEL_GUID) != 0) {
        logError(&tmp, "fmi2Instantiate: wrong GUID %s, expected %s.", fmuGUID ? fmuGUID : "NULL",
                 MODEL_GUID);
        return NULL;
    }
    S = (Instance *)calloc(1, sizeof(Instance));
    if (!S) return NULL;
    S->instanceName = (char *)calloc(strlen(instanceName) + 1, 1);
    if (!S->instanceName) {
        free(S);
        return NULL;
    }
    strcpy(S->instanceName, instanceName);
    S->logger = tmp.logger;
    S->env = tmp.env;
    S->logEvents = loggingOn ? 1 : 0;
    S->magic = INSTANCE_MAGIC;
    S->d.type = fmuType;
    S->d.state = Instantiated;
    setStartValues(S);
    return S;
}

void fmi2FreeInstance(fmi2Component c) {
    Instance *S = (Instance *)c;
    if (!S) return;
    if (invalidState(S, "fmi2FreeInstance", MASK_fmi2FreeInstance)) return;
    S->magic = 0;
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
    CHECK_STATE(fmi2SetupExperiment)
    if (!isfinite(startTime) || (stopTimeDefined && !(stopTime >= startTime))) {
        logError(S, "fmi2SetupExperiment: invalid start time %g or stop time %g.", startTime, stopTime);
        return fail(S);
    }
    S->d.time = startTime;
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
    double dx[NX];
    CHECK_STATE(fmi2ExitInitializationMode)
    /* evaluate once: parameters that make M(q0) singular are reported here */
    if (stateDerivatives(S, S->d.x, dx)) {
        logError(S, "fmi2ExitInitializationMode: the initial state cannot be evaluated.");
        return fail(S);
    }
    S->d.state = (S->d.type == fmi2ModelExchange) ? EventMode : StepComplete;
    logMessage(S, fmi2OK, "logEvents", "fmi2ExitInitializationMode: initialized at t = %g.", S->d.time);
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
    setStartValues(S);
    S->d.state = Instantiated;
    return fmi2OK;
}

/* ---------------------------------------------------------------- get and set values */

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    Instance *S = (Instance *)c;
    double dx[NX];
    int haveDx = 0;
    size_t i;
    CHECK_STATE(fmi2GetReal)
    if (nvr > 0 && (nullPointer(S, "fmi2GetReal", "vr[]", vr) || nullPointer(S, "fmi2GetReal", "value[]", value)))
        return fmi2Error;
    for (i = 0; i < nvr; i++) {
        fmi2ValueReference r = vr[i];
        if (r < VR_DER_Q) {
            value[i] = S->d.x[r - VR_Q];
        } else if (r < VR_DER_DQ) {
            value[i] = S->d.x[NQ + r - VR_DER_Q]; /* der(q) = dq */
        } else if (r < VR_TAU) {
            if (!haveDx) {
                if (stateDerivatives(S, S->d.x, dx)) return fail(S);
                haveDx = 1;
            }
            value[i] = dx[NQ + r - VR_DER_DQ];
        } else if (r < VR_P) {
            value[i] = S->d.u[r - VR_TAU];
        } else if (r < VR_SUBSTEP) {
            value[i] = S->d.p[r - VR_P];
        } else if (r == VR_SUBSTEP) {
            value[i] = S->d.h;
        } else {
            logError(S, "fmi2GetReal: unknown value reference %u.", r);
            return fail(S);
        }
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    Instance *S = (Instance *)c;
    const int beforeInit = S && (S->d.state & (Instantiated | InitializationMode));
    char name[64];
    size_t i;
    CHECK_STATE(fmi2SetReal)
    if (nvr > 0 && (nullPointer(S, "fmi2SetReal", "vr[]", vr) || nullPointer(S, "fmi2SetReal", "value[]", value)))
        return fmi2Error;
    for (i = 0; i < nvr; i++) { /* check everything first: no partial update on error */
        fmi2ValueReference r = vr[i];
        if (r > VR_SUBSTEP) {
            logError(S, "fmi2SetReal: unknown value reference %u.", r);
            return fail(S);
        }
        /* the name only for a message: snprintf on every call would dominate the cost of
         * setting the inputs in a simulation loop */
        if (r >= VR_DER_Q && r < VR_TAU) {
            vrName(r, name, sizeof(name));
            logError(S, "fmi2SetReal: %s is calculated and cannot be set.", name);
            return fail(S);
        }
        if ((r < VR_DER_Q || r >= VR_P) && !beforeInit) {
            vrName(r, name, sizeof(name));
            logError(S, "fmi2SetReal: %s can only be set before fmi2ExitInitializationMode.", name);
            return fail(S);
        }
        if (!isfinite(value[i])) {
            vrName(r, name, sizeof(name));
            logError(S, "fmi2SetReal: the value of %s is not finite.", name);
            return fail(S);
        }
        if (r == VR_SUBSTEP && !(value[i] > 0)) {
            logError(S, "fmi2SetReal: cs_substep must be > 0, got %g.", value[i]);
            return fail(S);
        }
    }
    for (i = 0; i < nvr; i++) {
        fmi2ValueReference r = vr[i];
        if (r < VR_DER_Q)        S->d.x[r - VR_Q] = value[i];
        else if (r < VR_P)       S->d.u[r - VR_TAU] = value[i];
        else if (r < VR_SUBSTEP) S->d.p[r - VR_P] = value[i];
        else                     S->d.h = value[i];
    }
    return fmi2OK;
}

/* there are no Integer, Boolean or String variables */
static fmi2Status noSuchVariables(Instance *S, const char *f, size_t nvr) {
    if (invalidState(S, f, MASK_AnyButStart)) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    logError(S, "%s: this FMU has no variables of this type.", f);
    return fail(S);
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    (void)vr; (void)value;
    return noSuchVariables((Instance *)c, "fmi2GetInteger", nvr);
}
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    (void)vr; (void)value;
    return noSuchVariables((Instance *)c, "fmi2GetBoolean", nvr);
}
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    (void)vr; (void)value;
    return noSuchVariables((Instance *)c, "fmi2GetString", nvr);
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    (void)vr; (void)value;
    return noSuchVariables((Instance *)c, "fmi2SetInteger", nvr);
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[]) {
    (void)vr; (void)value;
    return noSuchVariables((Instance *)c, "fmi2SetBoolean", nvr);
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    (void)vr; (void)value;
    return noSuchVariables((Instance *)c, "fmi2SetString", nvr);
}

/* ---------------------------------------------------------------- FMU state */

/* serialized form: header (magic, sizes) followed by the Data record */
#define STATE_MAGIC 0x49564452u /* "IVDR" */
typedef struct {
    unsigned int magic, nq, np, size;
} StateHeader;

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2GetFMUstate", "FMUstate", FMUstate)) return fmi2Error;
    if (!*FMUstate) { /* else: reuse the memory of a state returned before (FMI 2.0.4, 2.1.8) */
        *FMUstate = calloc(1, sizeof(Data));
        if (!*FMUstate) {
            logError(S, "fmi2GetFMUstate: out of memory.");
            return fail(S);
        }
    }
    memcpy(*FMUstate, &S->d, sizeof(Data));
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2SetFMUstate", "FMUstate", FMUstate)) return fmi2Error;
    if (((const Data *)FMUstate)->type != S->d.type) {
        logError(S, "fmi2SetFMUstate: the state belongs to an instance of another fmuType.");
        return fail(S);
    }
    memcpy(&S->d, FMUstate, sizeof(Data));
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2FMUstate)
    if (FMUstate) {
        free(*FMUstate);
        *FMUstate = NULL;
    }
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    Instance *S = (Instance *)c;
    (void)FMUstate;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2SerializedFMUstateSize", "size", size)) return fmi2Error;
    *size = sizeof(StateHeader) + sizeof(Data);
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[], size_t size) {
    Instance *S = (Instance *)c;
    StateHeader hd;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2SerializeFMUstate", "FMUstate", FMUstate) ||
        nullPointer(S, "fmi2SerializeFMUstate", "serializedState", serializedState))
        return fmi2Error;
    if (size < sizeof(StateHeader) + sizeof(Data)) {
        logError(S, "fmi2SerializeFMUstate: buffer too small (%lu bytes).", (unsigned long)size);
        return fail(S);
    }
    hd.magic = STATE_MAGIC;
    hd.nq = NQ;
    hd.np = NP;
    hd.size = (unsigned int)sizeof(Data);
    memcpy(serializedState, &hd, sizeof(hd));
    memcpy(serializedState + sizeof(hd), FMUstate, sizeof(Data));
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    Instance *S = (Instance *)c;
    StateHeader hd;
    CHECK_STATE(fmi2FMUstate)
    if (nullPointer(S, "fmi2DeSerializeFMUstate", "serializedState", serializedState) ||
        nullPointer(S, "fmi2DeSerializeFMUstate", "FMUstate", FMUstate))
        return fmi2Error;
    if (size >= sizeof(hd)) memcpy(&hd, serializedState, sizeof(hd));
    if (size != sizeof(hd) + sizeof(Data) || hd.magic != STATE_MAGIC || hd.nq != NQ || hd.np != NP ||
        hd.size != sizeof(Data)) {
        logError(S, "fmi2DeSerializeFMUstate: the data is not a serialized state of this FMU.");
        return fail(S);
    }
    if (!*FMUstate) {
        *FMUstate = calloc(1, sizeof(Data));
        if (!*FMUstate) {
            logError(S, "fmi2DeSerializeFMUstate: out of memory.");
            return fail(S);
        }
    }
    memcpy(*FMUstate, serializedState + sizeof(hd), sizeof(Data));
    return fmi2OK;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[], size_t nUnknown,
                                        const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[]) {
    Instance *S = (Instance *)c;
    (void)vUnknown_ref; (void)nUnknown; (void)vKnown_ref; (void)nKnown; (void)dvKnown; (void)dvUnknown;
    if (invalidState(S, "fmi2GetDirectionalDerivative", MASK_AnyButStart)) return fmi2Error;
    logError(S, "fmi2GetDirectionalDerivative is not provided (providesDirectionalDerivative=\"false\").");
    return fail(S);
}

/* ---------------------------------------------------------------- model exchange */

fmi2Status fmi2EnterEventMode(fmi2Component c) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2EnterEventMode)
    S->d.state = EventMode;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *eventInfo) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2NewDiscreteStates)
    if (nullPointer(S, "fmi2NewDiscreteStates", "eventInfo", eventInfo)) return fmi2Error;
    /* no discrete states, no events */
    eventInfo->newDiscreteStatesNeeded = fmi2False;
    eventInfo->terminateSimulation = fmi2False;
    eventInfo->nominalsOfContinuousStatesChanged = fmi2False;
    eventInfo->valuesOfContinuousStatesChanged = fmi2False;
    eventInfo->nextEventTimeDefined = fmi2False;
    eventInfo->nextEventTime = 0;
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2EnterContinuousTimeMode)
    S->d.state = ContinuousTimeMode;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminateSimulation) {
    Instance *S = (Instance *)c;
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK_STATE(fmi2CompletedIntegratorStep)
    if (nullPointer(S, "fmi2CompletedIntegratorStep", "enterEventMode", enterEventMode) ||
        nullPointer(S, "fmi2CompletedIntegratorStep", "terminateSimulation", terminateSimulation))
        return fmi2Error;
    *enterEventMode = fmi2False;
    *terminateSimulation = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2SetTime)
    if (!isfinite(time)) {
        logError(S, "fmi2SetTime: time is not finite.");
        return fail(S);
    }
    S->d.time = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    Instance *S = (Instance *)c;
    size_t i;
    CHECK_STATE(fmi2SetContinuousStates)
    if (nullPointer(S, "fmi2SetContinuousStates", "x[]", x)) return fmi2Error;
    if (nx != NX) {
        logError(S, "fmi2SetContinuousStates: nx = %lu, expected %d.", (unsigned long)nx, NX);
        return fail(S);
    }
    for (i = 0; i < NX; i++) {
        if (!isfinite(x[i])) {
            logError(S, "fmi2SetContinuousStates: x[%lu] is not finite.", (unsigned long)i);
            return fail(S);
        }
    }
    memcpy(S->d.x, x, sizeof(S->d.x));
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real derivatives[], size_t nx) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2GetDerivatives)
    if (nullPointer(S, "fmi2GetDerivatives", "derivatives[]", derivatives)) return fmi2Error;
    if (nx != NX) {
        logError(S, "fmi2GetDerivatives: nx = %lu, expected %d.", (unsigned long)nx, NX);
        return fail(S);
    }
    if (stateDerivatives(S, S->d.x, derivatives)) return fail(S);
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real eventIndicators[], size_t ni) {
    Instance *S = (Instance *)c;
    (void)eventIndicators;
    CHECK_STATE(fmi2GetEventIndicators)
    if (ni != 0) {
        logError(S, "fmi2GetEventIndicators: ni = %lu, but there are no event indicators.", (unsigned long)ni);
        return fail(S);
    }
    return fmi2OK;
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2GetContinuousStates)
    if (nullPointer(S, "fmi2GetContinuousStates", "x[]", x)) return fmi2Error;
    if (nx != NX) {
        logError(S, "fmi2GetContinuousStates: nx = %lu, expected %d.", (unsigned long)nx, NX);
        return fail(S);
    }
    memcpy(x, S->d.x, sizeof(S->d.x));
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[], size_t nx) {
    Instance *S = (Instance *)c;
    size_t i;
    CHECK_STATE(fmi2GetNominals)
    if (nullPointer(S, "fmi2GetNominalsOfContinuousStates", "x_nominal[]", x_nominal)) return fmi2Error;
    if (nx != NX) {
        logError(S, "fmi2GetNominalsOfContinuousStates: nx = %lu, expected %d.", (unsigned long)nx, NX);
        return fail(S);
    }
    for (i = 0; i < NX; i++) x_nominal[i] = 1.0;
    return fmi2OK;
}

/* ---------------------------------------------------------------- co-simulation */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    Instance *S = (Instance *)c;
    (void)vr; (void)order; (void)value;
    if (invalidState(S, "fmi2SetRealInputDerivatives", Instantiated | InitializationMode | StepComplete))
        return fmi2Error;
    if (nvr == 0) return fmi2OK;
    logError(S, "fmi2SetRealInputDerivatives: inputs are held constant (canInterpolateInputs=\"false\").");
    return fail(S);
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    Instance *S = (Instance *)c;
    (void)vr; (void)order; (void)value;
    if (invalidState(S, "fmi2GetRealOutputDerivatives", StepComplete | StepFailed | StepCanceled | Terminated | Error))
        return fmi2Error;
    if (nvr == 0) return fmi2OK;
    logError(S, "fmi2GetRealOutputDerivatives: not provided (maxOutputDerivativeOrder=\"0\").");
    return fail(S);
}

/* classical Runge-Kutta step of size dt (Hairer, Norsett & Wanner, Table 1.2) */
static int rk4(Instance *S, double *x, double dt) {
    double k1[NX], k2[NX], k3[NX], k4[NX], y[NX];
    int i;
    if (stateDerivatives(S, x, k1)) return 1;
    for (i = 0; i < NX; i++) y[i] = x[i] + 0.5 * dt * k1[i];
    if (stateDerivatives(S, y, k2)) return 1;
    for (i = 0; i < NX; i++) y[i] = x[i] + 0.5 * dt * k2[i];
    if (stateDerivatives(S, y, k3)) return 1;
    for (i = 0; i < NX; i++) y[i] = x[i] + dt * k3[i];
    if (stateDerivatives(S, y, k4)) return 1;
    for (i = 0; i < NX; i++) x[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
    return 0;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentCommunicationPoint) {
    Instance *S = (Instance *)c;
    double x[NX], t0, dt, nsub;
    long k, i;
    (void)noSetFMUStatePriorToCurrentCommunicationPoint;
    CHECK_STATE(fmi2DoStep)
    if (!isfinite(currentCommunicationPoint) || !isfinite(communicationStepSize) || communicationStepSize < 0) {
        logError(S, "fmi2DoStep: invalid communication point %g or step size %g.", currentCommunicationPoint,
                 communicationStepSize);
        return fail(S);
    }
    if (fabs(currentCommunicationPoint - S->d.time) > 1e-9 * (1.0 + fabs(S->d.time))) {
        logError(S, "fmi2DoStep: currentCommunicationPoint = %.17g differs from the FMU time %.17g.",
                 currentCommunicationPoint, S->d.time);
        return fail(S);
    }
    if (communicationStepSize == 0) return fmi2OK;
    nsub = ceil(communicationStepSize / S->d.h * (1.0 - 1e-12)); /* k = ceil(H/h) sub-steps */
    if (nsub > 1e9) {
        logError(S, "fmi2DoStep: %g RK4 sub-steps of at most cs_substep = %g needed: step too large.",
                 nsub, S->d.h);
        return fail(S);
    }
    k = nsub < 1 ? 1 : (long)nsub;
    dt = communicationStepSize / (double)k;
    memcpy(x, S->d.x, sizeof(x));
    t0 = currentCommunicationPoint;
    for (i = 0; i < k; i++) {
        S->d.time = t0 + (double)i * dt;
        if (rk4(S, x, dt)) {
            S->d.time = t0; /* the state is left at the start of the step */
            logError(S, "fmi2DoStep: the step from t = %g failed.", t0);
            return fail(S);
        }
    }
    memcpy(S->d.x, x, sizeof(x));
    S->d.time = t0 + communicationStepSize;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    Instance *S = (Instance *)c;
    if (invalidState(S, "fmi2CancelStep", StepInProgress)) return fmi2Error;
    return fmi2OK; /* unreachable: steps are synchronous (canRunAsynchronuously="false") */
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2GetStatus)
    if (nullPointer(S, "fmi2GetStatus", "value", value)) return fmi2Error;
    if (s != fmi2DoStepStatus) {
        logError(S, "fmi2GetStatus: status kind %d is not available.", (int)s);
        return fmi2Discard;
    }
    *value = fmi2OK; /* the last fmi2DoStep completed synchronously */
    return fmi2OK;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2GetStatus)
    if (nullPointer(S, "fmi2GetRealStatus", "value", value)) return fmi2Error;
    if (s != fmi2LastSuccessfulTime) {
        logError(S, "fmi2GetRealStatus: status kind %d is not available.", (int)s);
        return fmi2Discard;
    }
    *value = S->d.time;
    return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    Instance *S = (Instance *)c;
    (void)s; (void)value;
    CHECK_STATE(fmi2GetStatus)
    logError(S, "fmi2GetIntegerStatus: no integer status is available.");
    return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    Instance *S = (Instance *)c;
    CHECK_STATE(fmi2GetStatus)
    if (nullPointer(S, "fmi2GetBooleanStatus", "value", value)) return fmi2Error;
    if (s != fmi2Terminated) {
        logError(S, "fmi2GetBooleanStatus: status kind %d is not available.", (int)s);
        return fmi2Discard;
    }
    *value = fmi2False; /* the FMU never asks to terminate */
    return fmi2OK;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    Instance *S = (Instance *)c;
    (void)s; (void)value;
    CHECK_STATE(fmi2GetStatus)
    logError(S, "fmi2GetStringStatus: no string status is available.");
    return fmi2Discard;
}
