/* fmi_controller_common.h: what the FMI 2.0 (fmi2_controller.c) and FMI 3.0
 * (fmi3_controller.c) wrappers of the sampled controller library share: the instance, the
 * state machine checks, logging, value access by value reference, the step, and the save
 * and restore of the whole state (docs/controller.md, "Controller FMU").  Compiled as its
 * own translation unit into every controller FMU; each wrapper keeps only its FMI
 * version's entry points and maps its types onto these.
 *
 * Statuses are the common values of fmi2Status and fmi3Status (OK 0 ... Fatal 4), value
 * references are unsigned int (fmi2ValueReference and fmi3ValueReference alike); each
 * wrapper checks both at compile time.
 */
#ifndef FMI_CONTROLLER_COMMON_H
#define FMI_CONTROLLER_COMMON_H

#include <stddef.h>

#include "ivdrem_controller.h"

#define FC_OK 0
#define FC_WARNING 1
#define FC_DISCARD 2
#define FC_ERROR 3
#define FC_FATAL 4

/* The model states of the FMI Reference FMUs.  FMI 3.0 co-simulation uses Instantiated,
 * InitializationMode, StepMode, Terminated and Error; FMI 2.0 calls StepMode StepComplete
 * and also names StepFailed and StepCanceled (never entered: the step is synchronous). */
enum {
    FC_StartAndEnd = 1 << 0, FC_Instantiated = 1 << 1, FC_InitializationMode = 1 << 2,
    FC_StepMode = 1 << 5, FC_StepInProgress = 1 << 6, FC_StepFailed = 1 << 7,
    FC_StepCanceled = 1 << 8, FC_Terminated = 1 << 9, FC_Error = 1 << 10, FC_Fatal = 1 << 11
};
#define FC_ANY_BUT_START (FC_Instantiated | FC_InitializationMode | FC_StepMode | \
                          FC_StepFailed | FC_StepCanceled | FC_Terminated | FC_Error)

/* what an FMU state saves besides the controller's own state */
typedef struct {
    int state;
    int has_controller;
    double time;
    double in[2 * IVC_NQ];
    double par[IVC_NPAR];
    size_t csize;                       /* bytes of the controller state that follow */
} FcHead;

typedef struct FcInstance FcInstance;

/* hands one formatted message to the host's logger, with the logger's FMI signature */
typedef void (*FcEmit)(const FcInstance *S, int status, const char *category, const char *message);

struct FcInstance {
    unsigned int magic;
    FcHead d;
    ivc_controller *ctl;                /* created by ExitInitializationMode */
    char *instanceName;
    double ref0[2 * IVC_NQ];            /* q_d(0), dq_d(0): the reference before the first step */
    void (*logger)(void);               /* the host's callback; only emit calls it, cast back */
    void *env;
    FcEmit emit;
    int logEvents;
};

void fc_log(const FcInstance *S, int status, const char *category, const char *fmt, ...);
#define fc_error(S, ...) fc_log(S, FC_ERROR, "logStatusError", __VA_ARGS__)

/* 1 (and the instance in Error) when S is no instance or its state is not in mask */
int fc_invalid_state(FcInstance *S, const char *f, int mask);
int fc_null_pointer(FcInstance *S, const char *f, const char *arg, const void *p);
int fc_fail(FcInstance *S);

/* a stack instance that only logs, for the checks before an instance exists */
void fc_log_only(FcInstance *tmp, const char *instanceName, void (*logger)(void), void *env,
                 FcEmit emit);
/* a new instance in state Instantiated with the start values, or NULL */
FcInstance *fc_new(const FcInstance *tmp, const char *instanceName, int loggingOn);
void fc_free(FcInstance *S);

int fc_set_debug_logging(FcInstance *S, const char *f, int mask, int loggingOn,
                         size_t nCategories, const char *const categories[]);
int fc_check_start_time(FcInstance *S, const char *f, double startTime);
int fc_enter_initialization(FcInstance *S, const char *f);
int fc_exit_initialization(FcInstance *S, const char *f);
int fc_terminate(FcInstance *S, const char *f, int mask);
int fc_reset(FcInstance *S, const char *f, int mask);

/* Float64 / Real access; with_time: VR_TIME reads the time (FMI 3 independent variable) */
int fc_get_real(FcInstance *S, const char *f, int mask, const unsigned int vr[], size_t nvr,
                double value[], int with_time);
int fc_set_real(FcInstance *S, const char *f, int mask, const unsigned int vr[], size_t nvr,
                const double value[]);
/* the access functions of the types the FMU has no variables of */
int fc_no_such_variables(FcInstance *S, const char *f, int mask, size_t nvr);
/* the functions a capability flag of the modelDescription says are not provided */
int fc_not_provided(FcInstance *S, const char *f, int mask, const char *why);

/* FMU state: an opaque malloc'ed blob [size][FcHead][controller state] */
int fc_get_fmu_state(FcInstance *S, const char *f, int mask, void **state);
int fc_set_fmu_state(FcInstance *S, const char *f, int mask, const void *state);
int fc_free_fmu_state(FcInstance *S, const char *f, int mask, void **state);
int fc_serialized_size(FcInstance *S, const char *f, int mask, const void *state, size_t *size);
int fc_serialize(FcInstance *S, const char *f, int mask, const void *state, unsigned char *out,
                 size_t size);
int fc_deserialize(FcInstance *S, const char *f, int mask, const unsigned char *in, size_t size,
                   void **state);

/* The six FMU state entry points of an FMI version (names and types differ: fmi2GetFMUstate,
 * fmi3GetFMUState, fmi2DeSerializeFMUstate, fmi3DeserializeFMUState, ...), defined once. */
#define FC_FMU_STATE_ENTRY_POINTS(Status, Inst, FMUState, Byte, MASK, GET, SET, FREE, SIZE, SER, DESER) \
    Status GET(Inst c, FMUState *s) { return (Status)fc_get_fmu_state((FcInstance *)c, #GET, MASK, s); } \
    Status SET(Inst c, FMUState s) { return (Status)fc_set_fmu_state((FcInstance *)c, #SET, MASK, s); } \
    Status FREE(Inst c, FMUState *s) { return (Status)fc_free_fmu_state((FcInstance *)c, #FREE, MASK, s); } \
    Status SIZE(Inst c, FMUState s, size_t *size) \
        { return (Status)fc_serialized_size((FcInstance *)c, #SIZE, MASK, s, size); } \
    Status SER(Inst c, FMUState s, Byte out[], size_t size) \
        { return (Status)fc_serialize((FcInstance *)c, #SER, MASK, s, (unsigned char *)out, size); } \
    Status DESER(Inst c, const Byte in[], size_t size, FMUState *s) \
        { return (Status)fc_deserialize((FcInstance *)c, #DESER, MASK, (const unsigned char *)in, size, s); }

/* one sample: reads q, dq, computes tau (docs/controller.md, "Where the torque goes") */
int fc_do_step(FcInstance *S, const char *f, int mask, double currentCommunicationPoint,
               double communicationStepSize);

#endif
