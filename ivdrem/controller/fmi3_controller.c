/* fmi3_controller.c: FMI 3.0 co-simulation wrapper of the sampled controller library
 * (ivdrem_controller.c), shipped in every FMI 3.0 controller FMU that ivdrem exports
 * (ivdrem/controller/fmu_export.py, fmi_version=3).  Sizes, value references and names come
 * from the same generated controller_fmu.h as the FMI 2.0 wrapper fmi2_controller.c, and the
 * instance, state machine, logging, value access, step and FMU state are the same code,
 * fmi_controller_common.c (docs/controller.md): fmi3DoStep(t_k, h) reads q(t_k), dq(t_k)
 * and outputs tau_k from then on (delay 1); the step must equal the sample period h; an
 * illegal call or bad value is logged (category logStatusError) and returns fmi3Error.
 * This file holds the FMI 3.0 entry points, their state masks and the FMI 3.0 logger.
 */
#include <string.h>

#include "fmi3Functions.h"
#include "fmi_controller_common.h"
#include "controller_fmu.h"

/* the common statuses and value references are FMI 3.0's */
typedef char fc_status_is_fmi3[(FC_OK == fmi3OK && FC_WARNING == fmi3Warning && FC_DISCARD == fmi3Discard &&
                                FC_ERROR == fmi3Error && FC_FATAL == fmi3Fatal) ? 1 : -1];
typedef char fc_vr_is_fmi3[sizeof(fmi3ValueReference) == sizeof(unsigned int) ? 1 : -1];

#define ANY (FC_Instantiated | FC_InitializationMode | FC_StepMode | FC_Terminated | FC_Error)
#define MASK_GET (FC_InitializationMode | FC_StepMode | FC_Terminated | FC_Error)
#define MASK_SET (FC_Instantiated | FC_InitializationMode | FC_StepMode)
#define I(c) ((FcInstance *)(c))

static void emit3(const FcInstance *S, int status, const char *category, const char *message) {
    ((fmi3LogMessageCallback)S->logger)(S->env, (fmi3Status)status, category, message);
}

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
    fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn, fmi3Boolean eventModeUsed,
    fmi3Boolean earlyReturnAllowed, const fmi3ValueReference requiredIntermediateVariables[],
    size_t nRequiredIntermediateVariables, fmi3InstanceEnvironment instanceEnvironment,
    fmi3LogMessageCallback logMessageCb, fmi3IntermediateUpdateCallback intermediateUpdate) {
    FcInstance tmp;
    (void)resourcePath; (void)visible; (void)earlyReturnAllowed; (void)requiredIntermediateVariables;
    (void)nRequiredIntermediateVariables; (void)intermediateUpdate;
    fc_log_only(&tmp, instanceName, (void (*)(void))logMessageCb, instanceEnvironment, emit3);
    if (!instanceName || !instanceName[0]) { fc_error(&tmp, "fmi3InstantiateCoSimulation: missing instance name."); return NULL; }
    if (eventModeUsed) { fc_error(&tmp, "fmi3InstantiateCoSimulation: event mode is not supported."); return NULL; }
    if (!instantiationToken || strcmp(instantiationToken, MODEL_GUID) != 0) {
        fc_error(&tmp, "fmi3InstantiateCoSimulation: wrong instantiation token %s, expected %s.",
                 instantiationToken ? instantiationToken : "NULL", MODEL_GUID);
        return NULL;
    }
    return fc_new(&tmp, instanceName, loggingOn);
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
    if (!c || fc_invalid_state(I(c), "fmi3FreeInstance", ANY)) return;
    fc_free(I(c));
}

fmi3Status fmi3SetDebugLogging(fmi3Instance c, fmi3Boolean loggingOn, size_t nCategories, const fmi3String categories[]) {
    return (fmi3Status)fc_set_debug_logging(I(c), "fmi3SetDebugLogging", ANY, loggingOn, nCategories, categories);
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance c, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
    fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    const char *f = "fmi3EnterInitializationMode";
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    if (fc_invalid_state(I(c), f, FC_Instantiated)) return fmi3Error;
    if (fc_check_start_time(I(c), f, startTime) != FC_OK) return fmi3Error;
    return (fmi3Status)fc_enter_initialization(I(c), f);
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance c) {
    return (fmi3Status)fc_exit_initialization(I(c), "fmi3ExitInitializationMode");
}
fmi3Status fmi3Terminate(fmi3Instance c) { return (fmi3Status)fc_terminate(I(c), "fmi3Terminate", FC_StepMode); }
fmi3Status fmi3Reset(fmi3Instance c) { return (fmi3Status)fc_reset(I(c), "fmi3Reset", ANY); }

/* the state check, then the FMI 3 array-length check, before the common access */
static int badCount(fmi3Instance c, const char *f, int mask, size_t nvr, size_t nValues) {
    if (fc_invalid_state(I(c), f, mask)) return 1;
    if (nValues == nvr) return 0;
    fc_error(I(c), "%s: %lu values for %lu scalar variables.", f, (unsigned long)nValues, (unsigned long)nvr);
    fc_fail(I(c));
    return 1;
}

fmi3Status fmi3GetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Float64 value[], size_t nValues) {
    if (badCount(c, "fmi3GetFloat64", MASK_GET, nvr, nValues)) return fmi3Error;
    return (fmi3Status)fc_get_real(I(c), "fmi3GetFloat64", MASK_GET, vr, nvr, value, 1);
}
fmi3Status fmi3SetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Float64 value[], size_t nValues) {
    if (badCount(c, "fmi3SetFloat64", MASK_SET, nvr, nValues)) return fmi3Error;
    return (fmi3Status)fc_set_real(I(c), "fmi3SetFloat64", MASK_SET, vr, nvr, value);
}

#define NO_VARS(c, f, nvr) (fmi3Status)fc_no_such_variables(I(c), f, ANY, nvr)
#define NO_GET(T, TYPE) fmi3Status fmi3Get##T(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, TYPE value[], size_t nValues) \
    { (void)vr; (void)value; (void)nValues; return NO_VARS(c, "fmi3Get" #T, nvr); }
#define NO_SET(T, TYPE) fmi3Status fmi3Set##T(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const TYPE value[], size_t nValues) \
    { (void)vr; (void)value; (void)nValues; return NO_VARS(c, "fmi3Set" #T, nvr); }
#define NO_GETSET(T, TYPE) NO_GET(T, TYPE) NO_SET(T, TYPE)
NO_GETSET(Float32, fmi3Float32) NO_GETSET(Int8, fmi3Int8) NO_GETSET(UInt8, fmi3UInt8)
NO_GETSET(Int16, fmi3Int16) NO_GETSET(UInt16, fmi3UInt16) NO_GETSET(Int32, fmi3Int32)
NO_GETSET(UInt32, fmi3UInt32) NO_GETSET(Int64, fmi3Int64) NO_GETSET(UInt64, fmi3UInt64)
NO_GETSET(Boolean, fmi3Boolean) NO_GETSET(String, fmi3String)

fmi3Status fmi3GetBinary(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, size_t valueSizes[], fmi3Binary value[], size_t nValues)
    { (void)vr; (void)valueSizes; (void)value; (void)nValues; return NO_VARS(c, "fmi3GetBinary", nvr); }
fmi3Status fmi3SetBinary(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const size_t valueSizes[], const fmi3Binary value[], size_t nValues)
    { (void)vr; (void)valueSizes; (void)value; (void)nValues; return NO_VARS(c, "fmi3SetBinary", nvr); }
fmi3Status fmi3GetClock(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Clock values[])
    { (void)vr; (void)values; return NO_VARS(c, "fmi3GetClock", nvr); }
fmi3Status fmi3SetClock(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Clock values[])
    { (void)vr; (void)values; return NO_VARS(c, "fmi3SetClock", nvr); }

static fmi3Status unsupported(fmi3Instance c, const char *f) {
    return (fmi3Status)fc_not_provided(I(c), f, ANY, "not supported by this co-simulation FMU.");
}

/* ---------------------------------------------------------------- FMU state */

FC_FMU_STATE_ENTRY_POINTS(fmi3Status, fmi3Instance, fmi3FMUState, fmi3Byte, ANY,
                          fmi3GetFMUState, fmi3SetFMUState, fmi3FreeFMUState,
                          fmi3SerializedFMUStateSize, fmi3SerializeFMUState, fmi3DeserializeFMUState)

/* ---------------------------------------------------------------- co-simulation */

fmi3Status fmi3DoStep(fmi3Instance c, fmi3Float64 currentCommunicationPoint, fmi3Float64 communicationStepSize,
                      fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean *eventHandlingNeeded,
                      fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime) {
    int st;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (fc_invalid_state(I(c), "fmi3DoStep", FC_StepMode)) return fmi3Error;
    if (eventHandlingNeeded) *eventHandlingNeeded = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (earlyReturn) *earlyReturn = fmi3False;
    st = fc_do_step(I(c), "fmi3DoStep", FC_StepMode, currentCommunicationPoint, communicationStepSize);
    if (lastSuccessfulTime) *lastSuccessfulTime = I(c)->d.time;
    return (fmi3Status)st;
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
