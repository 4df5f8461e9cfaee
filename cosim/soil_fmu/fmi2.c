/* FMI 2.0 co-simulation API of the soil FMU: a thin layer over soil_fmu.c. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "soil_fmu.h"

typedef struct {
    Soil *soil;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment environment;
    char name[256];
} Fmu;

static const fmi2Status STATUS[] = {fmi2OK, fmi2Warning, fmi2Discard, fmi2Error};

/* FMI 2.0 loggers take a printf format: a '%' in the text must be doubled. */
static void log_fmi2(void *environment, SoilStatus status, const char *category, const char *message) {
    Fmu *fmu = (Fmu *)environment;
    size_t length = strlen(message), j = 0;
    char *escaped = malloc(2 * length + 1);
    if (!fmu->logger || !escaped) {
        free(escaped);
        return;
    }
    for (size_t i = 0; i < length; i++) {
        escaped[j++] = message[i];
        if (message[i] == '%') escaped[j++] = '%';
    }
    escaped[j] = 0;
    fmu->logger(fmu->environment, fmu->name, STATUS[status], category, escaped);
    free(escaped);
}

/* fmuResourceLocation is a file URI: file:///path, file://localhost/path or file:/path, percent-encoded. */
static char *path_of_uri(const char *uri) {
    const char *p = uri;
    char *path, *out;
    if (strncmp(p, "file://localhost/", 17) == 0) p += 16;
    else if (strncmp(p, "file:///", 8) == 0) p += 7;
    else if (strncmp(p, "file:/", 6) == 0) p += 5;
    else return NULL;
    path = out = malloc(strlen(p) + 1);
    if (!path) return NULL;
    for (; *p; p++) {
        unsigned code;
        if (p[0] == '%' && p[1] && p[2] && sscanf(p + 1, "%2x", &code) == 1) {
            *out++ = (char)code;
            p += 2;
        } else {
            *out++ = *p;
        }
    }
    *out = 0;
    return path;
}

#define SOIL(c) (((Fmu *)(c))->soil)
/* a call this FMU does not offer: an Error, logged, like every other */
#define REFUSE(c, call, why) STATUS[soil_refuse((c) ? SOIL(c) : NULL, call, why)]

FMI2_Export const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
FMI2_Export const char *fmi2GetVersion(void) { return fmi2Version; }

FMI2_Export fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                                           const fmi2String categories[]) {
    SOIL(c)->debug = loggingOn;
    return fmi2OK;
}

FMI2_Export fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                                          fmi2String fmuResourceLocation,
                                          const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                                          fmi2Boolean loggingOn) {
    Fmu *fmu = calloc(1, sizeof(Fmu));
    char *resources;
    if (!fmu) return NULL;
    fmu->logger = functions ? functions->logger : NULL;
    fmu->environment = functions ? functions->componentEnvironment : NULL;
    strncpy(fmu->name, instanceName ? instanceName : "soil", sizeof fmu->name - 1);
    if (fmuType != fmi2CoSimulation) {
        if (fmu->logger)
            fmu->logger(fmu->environment, fmu->name, fmi2Error, "logStatusError",
                        "the soil FMU supports co-simulation only");
        free(fmu);
        return NULL;
    }
    resources = fmuResourceLocation ? path_of_uri(fmuResourceLocation) : NULL;
    if (!resources && fmu->logger)
        fmu->logger(fmu->environment, fmu->name, fmi2Error, "logStatusError",
                    "fmuResourceLocation must be a file URI (file:///...)");
    fmu->soil = resources ? soil_new(fmu->name, resources, fmuGUID, log_fmi2, fmu, loggingOn) : NULL;
    free(resources);
    if (!fmu->soil) {
        free(fmu);
        return NULL;
    }
    return fmu;
}

FMI2_Export void fmi2FreeInstance(fmi2Component c) {
    if (!c) return;
    soil_free(SOIL(c));
    free(c);
}

FMI2_Export fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                                           fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    SOIL(c)->real[VR_TIME] = startTime;
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2EnterInitializationMode(fmi2Component c) { return fmi2OK; }
FMI2_Export fmi2Status fmi2ExitInitializationMode(fmi2Component c) { return STATUS[soil_start(SOIL(c))]; }

FMI2_Export fmi2Status fmi2Terminate(fmi2Component c) {
    soil_stop(SOIL(c));
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2Reset(fmi2Component c) {
    soil_reset(SOIL(c));
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    for (size_t i = 0; i < nvr; i++) {
        if (vr[i] == VR_TIME) /* FMI 3.0's independent variable; FMI 2.0 declares none */
            return REFUSE(c, "fmi2GetReal", "no Real variable has value reference 0 (the soil's time: "
                          "fmi2GetRealStatus(fmi2LastSuccessfulTime))");
        if (soil_get_real(SOIL(c), vr[i], &value[i]) != SOIL_OK) return fmi2Error;
    }
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                   const fmi2Real value[]) {
    for (size_t i = 0; i < nvr; i++)
        if (soil_set_real(SOIL(c), vr[i], value[i]) != SOIL_OK) return fmi2Error;
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                      fmi2Integer value[]) {
    for (size_t i = 0; i < nvr; i++)
        if (soil_get_integer(SOIL(c), vr[i], &value[i]) != SOIL_OK) return fmi2Error;
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                     fmi2String value[]) {
    for (size_t i = 0; i < nvr; i++)
        if (soil_get_string(SOIL(c), vr[i], &value[i]) != SOIL_OK) return fmi2Error;
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                     const fmi2String value[]) {
    for (size_t i = 0; i < nvr; i++)
        if (soil_set_string(SOIL(c), vr[i], value[i]) != SOIL_OK) return fmi2Error;
    return fmi2OK;
}

/* No Boolean variables, no settable Integer variables. */
FMI2_Export fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                      const fmi2Integer value[]) {
    return nvr ? REFUSE(c, "fmi2SetInteger", "no Integer variable is settable (the contact counts are outputs)") : fmi2OK;
}
FMI2_Export fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                      fmi2Boolean value[]) {
    return nvr ? REFUSE(c, "fmi2GetBoolean", "this FMU has no Boolean variable") : fmi2OK;
}
FMI2_Export fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                      const fmi2Boolean value[]) {
    return nvr ? REFUSE(c, "fmi2SetBoolean", "this FMU has no Boolean variable") : fmi2OK;
}

FMI2_Export fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                                  fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    return STATUS[soil_step(SOIL(c), currentCommunicationPoint, communicationStepSize)];
}

/* A refused (Discard) step leaves the soil at the step's start: the last successful time. */
FMI2_Export fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    if (s != fmi2LastSuccessfulTime)
        return REFUSE(c, "fmi2GetRealStatus", "the only Real status offered is fmi2LastSuccessfulTime");
    *value = SOIL(c)->real[VR_TIME];
    return fmi2OK;
}

/* After a Discard: false while a shorter retry can succeed; true once the same step was retried unchanged
 * and refused again (the soil is deterministic: the master should stop at the last successful time). */
FMI2_Export fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    if (s != fmi2Terminated)
        return REFUSE(c, "fmi2GetBooleanStatus", "the only Boolean status offered is fmi2Terminated");
    *value = SOIL(c)->terminated ? fmi2True : fmi2False;
    return fmi2OK;
}

/* FMU states: the soil snapshot the server keeps (no serialization). */
FMI2_Export fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *state) {
    return STATUS[soil_get_state(SOIL(c), (SoilSnapshot **)state)];
}
FMI2_Export fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate state) {
    return STATUS[soil_set_state(SOIL(c), (const SoilSnapshot *)state)];
}
FMI2_Export fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *state) {
    return STATUS[soil_free_state(SOIL(c), (SoilSnapshot **)state)];
}

/* Not offered: asynchronous steps, serialized FMU states, derivatives (modelDescription.xml says so). */
FMI2_Export fmi2Status fmi2CancelStep(fmi2Component c) {
    return REFUSE(c, "fmi2CancelStep", "steps are never asynchronous (canRunAsynchronuously is false)");
}
FMI2_Export fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    return REFUSE(c, "fmi2GetStatus", "steps are never asynchronous: no fmi2Status to ask for");
}
FMI2_Export fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    return REFUSE(c, "fmi2GetIntegerStatus", "no Integer status is offered");
}
FMI2_Export fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    return REFUSE(c, "fmi2GetStringStatus", "no String status is offered (fmi2PendingStatus: steps are never asynchronous)");
}
FMI2_Export fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate state, size_t *size) {
    return REFUSE(c, "fmi2SerializedFMUstateSize", "FMU states are not serializable (canSerializeFMUstate is false)");
}
FMI2_Export fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate state, fmi2Byte serialized[], size_t size) {
    return REFUSE(c, "fmi2SerializeFMUstate", "FMU states are not serializable (canSerializeFMUstate is false)");
}
FMI2_Export fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serialized[], size_t size, fmi2FMUstate *state) {
    return REFUSE(c, "fmi2DeSerializeFMUstate", "FMU states are not serializable (canSerializeFMUstate is false)");
}
FMI2_Export fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference unknowns[], size_t nUnknown, const fmi2ValueReference knowns[], size_t nKnown, const fmi2Real dvKnown[], fmi2Real dvUnknown[]) {
    return REFUSE(c, "fmi2GetDirectionalDerivative", "no directional derivatives (providesDirectionalDerivative is false)");
}
FMI2_Export fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer order[], const fmi2Real value[]) {
    return REFUSE(c, "fmi2SetRealInputDerivatives", "inputs are not interpolated (canInterpolateInputs is false)");
}
FMI2_Export fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer order[], fmi2Real value[]) {
    return REFUSE(c, "fmi2GetRealOutputDerivatives", "no output derivatives (maxOutputDerivativeOrder is 0)");
}
