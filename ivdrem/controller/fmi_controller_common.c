/* fmi_controller_common.c: the body of both controller FMU wrappers (fmi2_controller.c,
 * fmi3_controller.c); see fmi_controller_common.h.
 *
 * Structure and state machine follow the FMI Reference FMUs: every function checks the
 * state it is called in (the mask its wrapper passes), and an illegal call or a bad value
 * is logged (category logStatusError) and returns Error, never crashes.
 *
 * Timing (docs/controller.md, "Where the torque goes"): DoStep(t_k, h) reads the inputs
 * q(t_k), dq(t_k) and computes tau_k, which is the output from then on (the torque for
 * [t_k+1, t_k+2]): delay 1, no direct feedthrough, so every Jacobi host computes the same
 * loop.  The communication step must equal the controller's sample period h.  Before the
 * first step the torque output is 0.
 *
 * An FMU state copies the whole controller state, the window's ring of block sums
 * included (ivc_get_state); a restored FMU continues bit for bit.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi_controller_common.h"
#include "controller_fmu.h"

#define INSTANCE_MAGIC 0x1D4E3C7Bu

void fc_log(const FcInstance *S, int status, const char *category, const char *fmt, ...) {
    char buf[1024];
    va_list args;
    if (!S || !S->logger || !S->emit) return;
    if (status == FC_OK && !S->logEvents) return;
    va_start(args, fmt);
    vsnprintf(buf, sizeof(buf), fmt, args);
    va_end(args);
    S->emit(S, status, category, buf);
}

int fc_invalid_state(FcInstance *S, const char *f, int mask) {
    if (!S || S->magic != INSTANCE_MAGIC) return 1;
    if (!(S->d.state & mask)) {
        fc_error(S, "%s: illegal call sequence (not allowed in the current state).", f);
        S->d.state = FC_Error;
        return 1;
    }
    return 0;
}

int fc_null_pointer(FcInstance *S, const char *f, const char *arg, const void *p) {
    if (p) return 0;
    fc_error(S, "%s: invalid argument %s = NULL.", f, arg);
    S->d.state = FC_Error;
    return 1;
}

int fc_fail(FcInstance *S) {
    S->d.state = FC_Error;
    return FC_ERROR;
}

static void vrName(unsigned int vr, char *buf, size_t n) {
    if (vr < VR_DQ)              snprintf(buf, n, "q[%u]", vr - VR_Q);
    else if (vr < VR_TAU)        snprintf(buf, n, "dq[%u]", vr - VR_DQ);
    else if (vr < VR_THETA_HAT)  snprintf(buf, n, "tau[%u]", vr - VR_TAU);
    else if (vr < VR_TAU_D_HAT)  snprintf(buf, n, "theta_hat[%u]", vr - VR_THETA_HAT);
    else if (vr < VR_DELTA)      snprintf(buf, n, "tau_d_hat[%u]", vr - VR_TAU_D_HAT);
    else if (vr == VR_DELTA)     snprintf(buf, n, "Delta");
    else if (vr < VR_PAR + IVC_NPAR) snprintf(buf, n, "%s", PARAMETER_NAMES[vr - VR_PAR]);
    else if (vr < VR_DQ_D)       snprintf(buf, n, "q_d[%u]", vr - VR_Q_D);
    else if (vr < VR_DQ_D + IVC_NQ) snprintf(buf, n, "dq_d[%u]", vr - VR_DQ_D);
    else                         snprintf(buf, n, "#%u", vr);
}

static void setStartValues(FcInstance *S) {
    int i;
    ivc_default_params(S->d.par);
    for (i = 0; i < 2 * IVC_NQ; i++) S->d.in[i] = 0.0;
    S->d.time = 0.0;
}

void fc_log_only(FcInstance *tmp, const char *instanceName, void (*logger)(void), void *env,
                 FcEmit emit) {
    memset(tmp, 0, sizeof *tmp);
    tmp->instanceName = (char *)(instanceName ? instanceName : "?");
    tmp->logger = logger;
    tmp->env = env;
    tmp->emit = emit;
}

FcInstance *fc_new(const FcInstance *tmp, const char *instanceName, int loggingOn) {
    FcInstance *S = (FcInstance *)calloc(1, sizeof(FcInstance));
    if (!S) return NULL;
    S->instanceName = (char *)calloc(strlen(instanceName) + 1, 1);
    if (!S->instanceName) { free(S); return NULL; }
    strcpy(S->instanceName, instanceName);
    S->logger = tmp->logger;
    S->env = tmp->env;
    S->emit = tmp->emit;
    S->logEvents = loggingOn ? 1 : 0;
    S->magic = INSTANCE_MAGIC;
    S->d.state = FC_Instantiated;
    setStartValues(S);
    return S;
}

void fc_free(FcInstance *S) {
    S->magic = 0;
    ivc_free(S->ctl);
    free(S->instanceName);
    free(S);
}

int fc_set_debug_logging(FcInstance *S, const char *f, int mask, int loggingOn,
                         size_t nCategories, const char *const categories[]) {
    size_t i;
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (nCategories > 0 && fc_null_pointer(S, f, "categories", categories)) return FC_ERROR;
    for (i = 0; i < nCategories; i++) {
        if (!categories[i] || (strcmp(categories[i], "logEvents") != 0 &&
                               strcmp(categories[i], "logStatusError") != 0)) {
            fc_error(S, "%s: unknown log category %s.", f, categories[i] ? categories[i] : "NULL");
            return fc_fail(S);
        }
    }
    S->logEvents = loggingOn ? 1 : 0;
    return FC_OK;
}

int fc_check_start_time(FcInstance *S, const char *f, double startTime) {
    if (startTime == 0.0) return FC_OK;
    fc_error(S, "%s: the controller starts at t = 0 (its mu(t), F(t) and reference are "
                "functions of t), got start time %g.", f, startTime);
    return fc_fail(S);
}

int fc_enter_initialization(FcInstance *S, const char *f) {
    if (fc_invalid_state(S, f, FC_Instantiated)) return FC_ERROR;
    S->d.state = FC_InitializationMode;
    return FC_OK;
}

/* The reference at t = 0, before the first step (a host starts the arm on it): the library
 * gives the reference of its last step (ivc_reference), so one step is taken at t = 0 from
 * the inputs as set and the whole state is restored, bit for bit (ivc_get/set_state). */
static int referenceAtStart(FcInstance *S) {
    size_t size = ivc_state_size(S->ctl);
    void *buf = malloc(size);
    double tau[IVC_NQ];
    int ok;
    if (!buf) return 0;
    ok = ivc_get_state(S->ctl, buf, size) == IVC_OK &&
         ivc_step(S->ctl, 0.0, S->d.in, S->d.in + IVC_NQ, tau) == IVC_OK &&
         ivc_reference(S->ctl, S->ref0, S->ref0 + IVC_NQ) == IVC_OK;
    ok = ivc_set_state(S->ctl, buf, size) == IVC_OK && ok;
    free(buf);
    return ok;
}

int fc_exit_initialization(FcInstance *S, const char *f) {
    char msg[256];
    if (fc_invalid_state(S, f, FC_InitializationMode)) return FC_ERROR;
    ivc_free(S->ctl);
    S->ctl = ivc_init(S->d.par, msg, sizeof msg);        /* the allocations: here, and */
    if (!S->ctl) {
        fc_error(S, "%s: %s.", f, msg);
        return fc_fail(S);
    }
    if (!referenceAtStart(S)) {                          /* a copy of the state, freed */
        fc_error(S, "%s: the reference at t = 0: %s.", f, ivc_message(S->ctl));
        return fc_fail(S);
    }
    S->d.has_controller = 1;
    S->d.time = 0.0;
    S->d.state = FC_StepMode;
    fc_log(S, FC_OK, "logEvents", "%s: window of %lu bytes.", f,
           (unsigned long)ivc_window_bytes(S->ctl));
    return FC_OK;
}

int fc_terminate(FcInstance *S, const char *f, int mask) {
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    S->d.state = FC_Terminated;
    return FC_OK;
}

int fc_reset(FcInstance *S, const char *f, int mask) {
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    ivc_free(S->ctl);
    S->ctl = NULL;
    S->d.has_controller = 0;
    setStartValues(S);
    S->d.state = FC_Instantiated;
    return FC_OK;
}

/* ---------------------------------------------------------------- values */

static int checkArrays(FcInstance *S, const char *f, size_t nvr, const void *vr, const void *value) {
    return nvr > 0 && (fc_null_pointer(S, f, "vr[]", vr) || fc_null_pointer(S, f, "value[]", value));
}

int fc_get_real(FcInstance *S, const char *f, int mask, const unsigned int vr[], size_t nvr,
                double value[], int with_time) {
    double th[IVC_NTHETA], tdh[IVC_NQ], D = 0.0, tau[IVC_NQ], ref[2 * IVC_NQ];
    size_t i;
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (checkArrays(S, f, nvr, vr, value)) return FC_ERROR;
    if (S->ctl) {
        ivc_outputs(S->ctl, th, tdh, &D, tau);
        /* q_d, dq_d: the reference of the last step (the one tau was computed for); before
         * the first step, the reference at t = 0 */
        if (ivc_time(S->ctl) > 0.0) ivc_reference(S->ctl, ref, ref + IVC_NQ);
        else memcpy(ref, S->ref0, sizeof ref);
    } else {
        for (i = 0; i < IVC_NTHETA; i++) th[i] = S->d.par[IVC_P_THETA_HAT0 + i];
        for (i = 0; i < IVC_NQ; i++) tdh[i] = tau[i] = 0.0;
        for (i = 0; i < 2 * IVC_NQ; i++) ref[i] = 0.0;
    }
    for (i = 0; i < nvr; i++) {
        unsigned int r = vr[i];
        if (r < VR_TAU) value[i] = S->d.in[r];
        else if (r < VR_THETA_HAT) value[i] = tau[r - VR_TAU];
        else if (r < VR_TAU_D_HAT) value[i] = th[r - VR_THETA_HAT];
        else if (r < VR_DELTA) value[i] = tdh[r - VR_TAU_D_HAT];
        else if (r == VR_DELTA) value[i] = D;
        else if (r < VR_PAR + IVC_NPAR) value[i] = S->ctl ? ivc_get_param(S->ctl, (int)(r - VR_PAR)) : S->d.par[r - VR_PAR];
        else if (r < VR_Q_D + 2 * IVC_NQ) value[i] = ref[r - VR_Q_D];
        else if (with_time && r == VR_TIME) value[i] = S->d.time;
        else {
            fc_error(S, "%s: unknown value reference %u.", f, r);
            return fc_fail(S);
        }
    }
    return FC_OK;
}

int fc_set_real(FcInstance *S, const char *f, int mask, const unsigned int vr[], size_t nvr,
                const double value[]) {
    char name[64];
    size_t i;
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (checkArrays(S, f, nvr, vr, value)) return FC_ERROR;
    for (i = 0; i < nvr; i++) {
        unsigned int r = vr[i];
        vrName(r, name, sizeof name);
        if (r < VR_TAU) {
            if (!isfinite(value[i])) {
                fc_error(S, "%s: %s = %g is not finite.", f, name, value[i]);
                return fc_fail(S);
            }
            S->d.in[r] = value[i];
        } else if (r >= VR_PAR && r < VR_PAR + IVC_NPAR) {
            int k = (int)(r - VR_PAR);
            if (!PARAMETER_EXPOSED[k]) {
                fc_error(S, "%s: %s is fixed in this FMU.", f, name);
                return fc_fail(S);
            }
            if (isnan(value[i])) {
                fc_error(S, "%s: %s is NaN.", f, name);
                return fc_fail(S);
            }
            if (S->d.state == FC_StepMode) {
                /* between steps only the tunable gains may change (modelDescription
                 * variability="tunable"); ivc_set_param checks the new value */
                if (!PARAMETER_TUNABLE[k]) {
                    fc_error(S, "%s: parameter %s is fixed after initialization.", f, name);
                    return fc_fail(S);
                }
                if (ivc_set_param(S->ctl, k, value[i]) != IVC_OK) {
                    fc_error(S, "%s: %s = %g refused: %s.", f, name, value[i], ivc_message(S->ctl));
                    return fc_fail(S);
                }
            }
            S->d.par[k] = value[i];
        } else {
            fc_error(S, "%s: %s cannot be set (an output or unknown).", f, name);
            return fc_fail(S);
        }
    }
    return FC_OK;
}

int fc_no_such_variables(FcInstance *S, const char *f, int mask, size_t nvr) {
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (nvr == 0) return FC_OK;
    fc_error(S, "%s: the FMU has no variables of this type.", f);
    return fc_fail(S);
}

int fc_not_provided(FcInstance *S, const char *f, int mask, const char *why) {
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    fc_error(S, "%s: %s", f, why);
    return fc_fail(S);
}

/* ---------------------------------------------------------------- FMU state */

static size_t stateBytes(const FcInstance *S) {
    return sizeof(FcHead) + (S->ctl ? ivc_state_size(S->ctl) : 0);
}

static void saveTo(const FcInstance *S, unsigned char *buf) {
    FcHead h = S->d;
    h.csize = S->ctl ? ivc_state_size(S->ctl) : 0;
    memcpy(buf, &h, sizeof h);
    if (S->ctl) ivc_get_state(S->ctl, buf + sizeof h, h.csize);
}

static int restoreFrom(FcInstance *S, const char *f, const unsigned char *buf, size_t size) {
    FcHead h;
    char msg[256];
    if (size < sizeof h) { fc_error(S, "%s: state of %lu bytes is too short.", f, (unsigned long)size); return fc_fail(S); }
    memcpy(&h, buf, sizeof h);
    if (size != sizeof h + h.csize || (h.has_controller && h.csize == 0)) {
        fc_error(S, "%s: inconsistent state (%lu bytes).", f, (unsigned long)size);
        return fc_fail(S);
    }
    if (h.has_controller) {
        if (!S->ctl || ivc_state_size(S->ctl) != h.csize) {
            ivc_free(S->ctl);
            S->ctl = ivc_init(h.par, msg, sizeof msg);
            if (!S->ctl) { fc_error(S, "%s: %s.", f, msg); return fc_fail(S); }
        }
        if (ivc_set_state(S->ctl, buf + sizeof h, h.csize) != IVC_OK) {
            fc_error(S, "%s: %s.", f, ivc_message(S->ctl));
            return fc_fail(S);
        }
    } else {
        ivc_free(S->ctl);
        S->ctl = NULL;
    }
    S->d = h;
    return FC_OK;
}

int fc_get_fmu_state(FcInstance *S, const char *f, int mask, void **state) {
    size_t *blob;
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (fc_null_pointer(S, f, "FMUstate", state)) return FC_ERROR;
    if (*state) free(*state);
    blob = (size_t *)malloc(sizeof(size_t) + stateBytes(S));   /* [size][FcHead][controller] */
    if (!blob) { fc_error(S, "%s: out of memory.", f); return fc_fail(S); }
    blob[0] = stateBytes(S);
    saveTo(S, (unsigned char *)(blob + 1));
    *state = blob;
    return FC_OK;
}

int fc_set_fmu_state(FcInstance *S, const char *f, int mask, const void *state) {
    const size_t *blob = (const size_t *)state;
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (fc_null_pointer(S, f, "FMUstate", state)) return FC_ERROR;
    return restoreFrom(S, f, (const unsigned char *)(blob + 1), blob[0]);
}

int fc_free_fmu_state(FcInstance *S, const char *f, int mask, void **state) {
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (fc_null_pointer(S, f, "FMUstate", state)) return FC_ERROR;
    free(*state);
    *state = NULL;
    return FC_OK;
}

int fc_serialized_size(FcInstance *S, const char *f, int mask, const void *state, size_t *size) {
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (fc_null_pointer(S, f, "FMUstate", state) || fc_null_pointer(S, f, "size", size)) return FC_ERROR;
    *size = ((const size_t *)state)[0];
    return FC_OK;
}

int fc_serialize(FcInstance *S, const char *f, int mask, const void *state, unsigned char *out,
                 size_t size) {
    const size_t *blob = (const size_t *)state;
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (fc_null_pointer(S, f, "FMUstate", state) ||
        fc_null_pointer(S, f, "serializedState", out)) return FC_ERROR;
    if (size != blob[0]) {
        fc_error(S, "%s: buffer of %lu bytes, the state has %lu.", f, (unsigned long)size,
                 (unsigned long)blob[0]);
        return fc_fail(S);
    }
    memcpy(out, blob + 1, size);
    return FC_OK;
}

int fc_deserialize(FcInstance *S, const char *f, int mask, const unsigned char *in, size_t size,
                   void **state) {
    size_t *blob;
    FcHead h;
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    if (fc_null_pointer(S, f, "serializedState", in) ||
        fc_null_pointer(S, f, "FMUstate", state)) return FC_ERROR;
    if (size < sizeof h) { fc_error(S, "%s: %lu bytes is too short.", f, (unsigned long)size); return fc_fail(S); }
    memcpy(&h, in, sizeof h);
    if (size != sizeof h + h.csize) {
        fc_error(S, "%s: %lu bytes, the state says %lu.", f, (unsigned long)size,
                 (unsigned long)(sizeof h + h.csize));
        return fc_fail(S);
    }
    blob = (size_t *)malloc(sizeof(size_t) + size);
    if (!blob) { fc_error(S, "%s: out of memory.", f); return fc_fail(S); }
    blob[0] = size;
    memcpy(blob + 1, in, size);
    if (*state) free(*state);
    *state = blob;
    return FC_OK;
}

/* ---------------------------------------------------------------- co-simulation */

int fc_do_step(FcInstance *S, const char *f, int mask, double currentCommunicationPoint,
               double communicationStepSize) {
    double tau[IVC_NQ], h;
    int st;
    if (fc_invalid_state(S, f, mask)) return FC_ERROR;
    h = S->d.par[IVC_P_H];
    if (!(fabs(communicationStepSize - h) <= 1e-9 * h)) {
        fc_error(S, "%s: communication step %g must equal the controller's sample period h = %g.",
                 f, communicationStepSize, h);
        return fc_fail(S);
    }
    if (!(fabs(currentCommunicationPoint - S->d.time) <= 1e-9 * (S->d.time > 1 ? S->d.time : 1))) {
        fc_error(S, "%s: communication point %.17g, but the FMU is at t = %.17g.", f,
                 currentCommunicationPoint, S->d.time);
        return fc_fail(S);
    }
    st = ivc_step(S->ctl, ivc_time(S->ctl), S->d.in, S->d.in + IVC_NQ, tau);
    if (st != IVC_OK) {
        fc_error(S, "%s at t = %g: %s.", f, currentCommunicationPoint, ivc_message(S->ctl));
        return fc_fail(S);
    }
    S->d.time = ivc_time(S->ctl);
    return FC_OK;
}
