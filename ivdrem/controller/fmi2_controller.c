/* fmi2_controller.c: FMI 2.0 co-simulation wrapper of the sampled controller library
 * (ivdrem_controller.c), shipped unchanged in every controller FMU that ivdrem exports
 * (ivdrem/controller/fmu_export.py); sizes, value references and names come from the
 * generated controller_fmu.h.
 *
 * The instance, state machine, logging, value access, step and FMU state are those of
 * fmi_controller_common.c, shared with the FMI 3.0 wrapper; this file holds the FMI 2.0
 * entry points, their state masks (as in the FMI Reference FMUs) and the FMI 2.0 logger.
 *
 * Timing (docs/controller.md, "Where the torque goes"): fmi2DoStep(t_k, h) reads the
 * inputs q(t_k), dq(t_k) and computes tau_k, which is the output from then on (delay 1, no
 * direct feedthrough).  The communication step must equal the controller's sample period h.
 */
#include <string.h>

#include "fmi2Functions.h"
#include "fmi_controller_common.h"
#include "controller_fmu.h"

/* the common statuses and value references are FMI 2.0's */
typedef char fc_status_is_fmi2[(FC_OK == fmi2OK && FC_WARNING == fmi2Warning && FC_DISCARD == fmi2Discard &&
                                FC_ERROR == fmi2Error && FC_FATAL == fmi2Fatal) ? 1 : -1];
typedef char fc_vr_is_fmi2[sizeof(fmi2ValueReference) == sizeof(unsigned int) ? 1 : -1];

#define StepComplete FC_StepMode
#define MASK_fmi2FreeInstance            FC_ANY_BUT_START
#define MASK_fmi2SetDebugLogging         FC_ANY_BUT_START
#define MASK_fmi2SetupExperiment         FC_Instantiated
#define MASK_fmi2Terminate               (StepComplete | FC_StepFailed)
#define MASK_fmi2Reset                   FC_ANY_BUT_START
#define MASK_fmi2GetReal                 (FC_InitializationMode | StepComplete | FC_StepFailed | \
                                          FC_StepCanceled | FC_Terminated | FC_Error)
#define MASK_fmi2SetReal                 (FC_Instantiated | FC_InitializationMode | StepComplete)
#define MASK_fmi2FMUstate                FC_ANY_BUT_START
#define MASK_fmi2DoStep                  StepComplete
#define MASK_fmi2GetStatus               (StepComplete | FC_StepInProgress | FC_StepFailed | FC_Terminated)

#define I(c) ((FcInstance *)(c))

/* FMI 2.0's logger formats its message printf-style: a '%' of the text is doubled */
static void emit2(const FcInstance *S, int status, const char *category, const char *message) {
    char msg[2048];
    size_t i, j;
    for (i = 0, j = 0; message[i] && j + 2 < sizeof(msg); i++) {
        if (message[i] == '%') msg[j++] = '%';
        msg[j++] = message[i];
    }
    msg[j] = '\0';
    ((fmi2CallbackLogger)S->logger)(S->env, S->instanceName, (fmi2Status)status, category, msg);
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    FcInstance tmp;
    (void)fmuResourceLocation;
    (void)visible;
    fc_log_only(&tmp, instanceName, functions ? (void (*)(void))functions->logger : NULL,
                functions ? functions->componentEnvironment : NULL, emit2);
    if (!instanceName || !instanceName[0]) {
        fc_error(&tmp, "fmi2Instantiate: missing instance name.");
        return NULL;
    }
    if (fmuType != fmi2CoSimulation) {
        fc_error(&tmp, "fmi2Instantiate: the controller is a co-simulation FMU only (fmuType %d).", (int)fmuType);
        return NULL;
    }
    if (!fmuGUID || strcmp(fmuGUID, MODEL_GUID) != 0) {
        fc_error(&tmp, "fmi2Instantiate: wrong GUID %s, expected %s.", fmuGUID ? fmuGUID : "NULL", MODEL_GUID);
        return NULL;
    }
    return fc_new(&tmp, instanceName, loggingOn);
}

void fmi2FreeInstance(fmi2Component c) {
    if (!c || fc_invalid_state(I(c), "fmi2FreeInstance", MASK_fmi2FreeInstance)) return;
    fc_free(I(c));
}

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    return (fmi2Status)fc_set_debug_logging(I(c), "fmi2SetDebugLogging", MASK_fmi2SetDebugLogging,
                                            loggingOn, nCategories, categories);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTime; (void)stopTimeDefined;
    if (fc_invalid_state(I(c), "fmi2SetupExperiment", MASK_fmi2SetupExperiment)) return fmi2Error;
    return (fmi2Status)fc_check_start_time(I(c), "fmi2SetupExperiment", startTime);
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    return (fmi2Status)fc_enter_initialization(I(c), "fmi2EnterInitializationMode");
}
fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    return (fmi2Status)fc_exit_initialization(I(c), "fmi2ExitInitializationMode");
}
fmi2Status fmi2Terminate(fmi2Component c) {
    return (fmi2Status)fc_terminate(I(c), "fmi2Terminate", MASK_fmi2Terminate);
}
fmi2Status fmi2Reset(fmi2Component c) {
    return (fmi2Status)fc_reset(I(c), "fmi2Reset", MASK_fmi2Reset);
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    return (fmi2Status)fc_get_real(I(c), "fmi2GetReal", MASK_fmi2GetReal, vr, nvr, value, 0);
}
fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    return (fmi2Status)fc_set_real(I(c), "fmi2SetReal", MASK_fmi2SetReal, vr, nvr, value);
}

#define NO_ACCESS(F, TYPE, MASK) fmi2Status F(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, TYPE value[]) \
    { (void)vr; (void)value; return (fmi2Status)fc_no_such_variables(I(c), #F, MASK, nvr); }
NO_ACCESS(fmi2GetInteger, fmi2Integer, MASK_fmi2GetReal)
NO_ACCESS(fmi2GetBoolean, fmi2Boolean, MASK_fmi2GetReal)
NO_ACCESS(fmi2GetString, fmi2String, MASK_fmi2GetReal)
NO_ACCESS(fmi2SetInteger, const fmi2Integer, MASK_fmi2SetReal)
NO_ACCESS(fmi2SetBoolean, const fmi2Boolean, MASK_fmi2SetReal)
NO_ACCESS(fmi2SetString, const fmi2String, MASK_fmi2SetReal)

/* ---------------------------------------------------------------- FMU state */

FC_FMU_STATE_ENTRY_POINTS(fmi2Status, fmi2Component, fmi2FMUstate, fmi2Byte, MASK_fmi2FMUstate,
                          fmi2GetFMUstate, fmi2SetFMUstate, fmi2FreeFMUstate,
                          fmi2SerializedFMUstateSize, fmi2SerializeFMUstate, fmi2DeSerializeFMUstate)

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[], size_t nUnknown,
                                        const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[]) {
    (void)vUnknown_ref; (void)nUnknown; (void)vKnown_ref; (void)nKnown; (void)dvKnown; (void)dvUnknown;
    return (fmi2Status)fc_not_provided(I(c), "fmi2GetDirectionalDerivative", FC_ANY_BUT_START,
                                       "not provided (providesDirectionalDerivative=\"false\").");
}

/* ---------------------------------------------------------------- co-simulation */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    return (fmi2Status)fc_not_provided(I(c), "fmi2SetRealInputDerivatives", FC_ANY_BUT_START,
                                       "canInterpolateInputs=\"false\".");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    return (fmi2Status)fc_not_provided(I(c), "fmi2GetRealOutputDerivatives", FC_ANY_BUT_START,
                                       "maxOutputDerivativeOrder=\"0\".");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    (void)noSetFMUStatePriorToCurrentPoint;
    return (fmi2Status)fc_do_step(I(c), "fmi2DoStep", MASK_fmi2DoStep, currentCommunicationPoint,
                                  communicationStepSize);
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    return (fmi2Status)fc_not_provided(I(c), "fmi2CancelStep", FC_ANY_BUT_START,
                                       "fmi2DoStep is synchronous; there is no step to cancel.");
}

/* the status of the last step: it always completed (fmi2DoStep is synchronous) */
static int statusCall(fmi2Component c, const char *f, const void *value) {
    if (fc_invalid_state(I(c), f, MASK_fmi2GetStatus)) return 1;
    return value ? 0 : fc_null_pointer(I(c), f, "value", value);
}
static fmi2Status notProvided(fmi2Component c, const char *f, fmi2StatusKind s) {
    fc_error(I(c), "%s: status kind %d is not provided.", f, (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    if (statusCall(c, "fmi2GetStatus", value)) return fmi2Error;
    if (s == fmi2DoStepStatus) { *value = fmi2OK; return fmi2OK; }
    return notProvided(c, "fmi2GetStatus", s);
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    if (statusCall(c, "fmi2GetRealStatus", value)) return fmi2Error;
    if (s == fmi2LastSuccessfulTime) { *value = I(c)->d.time; return fmi2OK; }
    return notProvided(c, "fmi2GetRealStatus", s);
}
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    if (statusCall(c, "fmi2GetBooleanStatus", value)) return fmi2Error;
    if (s == fmi2Terminated) { *value = fmi2False; return fmi2OK; }
    return notProvided(c, "fmi2GetBooleanStatus", s);
}
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)value;
    if (fc_invalid_state(I(c), "fmi2GetIntegerStatus", MASK_fmi2GetStatus)) return fmi2Error;
    return notProvided(c, "fmi2GetIntegerStatus", s);
}
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)value;
    if (fc_invalid_state(I(c), "fmi2GetStringStatus", MASK_fmi2GetStatus)) return fmi2Error;
    return notProvided(c, "fmi2GetStringStatus", s);
}
