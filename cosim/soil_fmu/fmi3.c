/* FMI 3.0 co-simulation API of the soil FMU: a thin layer over soil_fmu.c. */
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "soil_fmu.h"

typedef struct {
    Soil *soil;
    fmi3LogMessageCallback logger;
    fmi3InstanceEnvironment environment;
    int early_return_allowed; /* the importer reads earlyReturn (fmi3InstantiateCoSimulation) */
} Fmu;

static const fmi3Status STATUS[] = {fmi3OK, fmi3Warning, fmi3Discard, fmi3Error};

static void log_fmi3(void *environment, SoilStatus status, const char *category, const char *message) {
    Fmu *fmu = (Fmu *)environment;
    if (fmu->logger) fmu->logger(fmu->environment, STATUS[status], category, message);
}

#define SOIL(instance) (((Fmu *)(instance))->soil)
/* a call this FMU does not offer, or whose arguments it cannot take: an Error, logged, like every other */
#define REFUSE(instance, call, why) STATUS[soil_refuse((instance) ? SOIL(instance) : NULL, call, why)]
/* every variable is a scalar: one value per value reference */
#define SCALARS(call, nvr, n) \
    if ((nvr) != (n)) return REFUSE(instance, call, "every variable is a scalar: nValues must equal nValueReferences")

FMI3_Export const char *fmi3GetVersion(void) { return fmi3Version; }

FMI3_Export fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                                           const fmi3String categories[]) {
    SOIL(instance)->debug = loggingOn;
    return fmi3OK;
}

FMI3_Export fmi3Instance fmi3InstantiateCoSimulation(
    fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath, fmi3Boolean visible,
    fmi3Boolean loggingOn, fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
    const fmi3ValueReference requiredIntermediateVariables[], size_t nRequiredIntermediateVariables,
    fmi3InstanceEnvironment instanceEnvironment, fmi3LogMessageCallback logMessage,
    fmi3IntermediateUpdateCallback intermediateUpdate) {
    Fmu *fmu = calloc(1, sizeof(Fmu));
    if (!fmu) return NULL;
    fmu->logger = logMessage;
    fmu->environment = instanceEnvironment;
    fmu->early_return_allowed = earlyReturnAllowed;
    fmu->soil = soil_new(instanceName, resourcePath, instantiationToken, log_fmi3, fmu, loggingOn);
    if (!fmu->soil) {
        free(fmu);
        return NULL;
    }
    return fmu;
}

FMI3_Export void fmi3FreeInstance(fmi3Instance instance) {
    if (!instance) return;
    soil_free(SOIL(instance));
    free(instance);
}

FMI3_Export fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined,
                                                   fmi3Float64 tolerance, fmi3Float64 startTime,
                                                   fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    SOIL(instance)->real[VR_TIME] = startTime;
    return fmi3OK;
}

FMI3_Export fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) {
    return STATUS[soil_start(SOIL(instance))];
}

FMI3_Export fmi3Status fmi3EnterStepMode(fmi3Instance instance) { return fmi3OK; }

FMI3_Export fmi3Status fmi3Terminate(fmi3Instance instance) {
    soil_stop(SOIL(instance));
    return fmi3OK;
}

FMI3_Export fmi3Status fmi3Reset(fmi3Instance instance) {
    soil_reset(SOIL(instance));
    return fmi3OK;
}

FMI3_Export fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                      size_t nValueReferences, fmi3Float64 values[], size_t nValues) {
    SCALARS("fmi3GetFloat64", nValueReferences, nValues);
    for (size_t i = 0; i < nValueReferences; i++)
        if (soil_get_real(SOIL(instance), valueReferences[i], &values[i]) != SOIL_OK) return fmi3Error;
    return fmi3OK;
}

FMI3_Export fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                      size_t nValueReferences, const fmi3Float64 values[], size_t nValues) {
    SCALARS("fmi3SetFloat64", nValueReferences, nValues);
    for (size_t i = 0; i < nValueReferences; i++)
        if (soil_set_real(SOIL(instance), valueReferences[i], values[i]) != SOIL_OK) return fmi3Error;
    return fmi3OK;
}

FMI3_Export fmi3Status fmi3GetInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                    size_t nValueReferences, fmi3Int32 values[], size_t nValues) {
    SCALARS("fmi3GetInt32", nValueReferences, nValues);
    for (size_t i = 0; i < nValueReferences; i++) {
        int value;
        if (soil_get_integer(SOIL(instance), valueReferences[i], &value) != SOIL_OK) return fmi3Error;
        values[i] = value;
    }
    return fmi3OK;
}

FMI3_Export fmi3Status fmi3GetString(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                     size_t nValueReferences, fmi3String values[], size_t nValues) {
    SCALARS("fmi3GetString", nValueReferences, nValues);
    for (size_t i = 0; i < nValueReferences; i++)
        if (soil_get_string(SOIL(instance), valueReferences[i], &values[i]) != SOIL_OK) return fmi3Error;
    return fmi3OK;
}

FMI3_Export fmi3Status fmi3SetString(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                     size_t nValueReferences, const fmi3String values[], size_t nValues) {
    SCALARS("fmi3SetString", nValueReferences, nValues);
    for (size_t i = 0; i < nValueReferences; i++)
        if (soil_set_string(SOIL(instance), valueReferences[i], values[i]) != SOIL_OK) return fmi3Error;
    return fmi3OK;
}

/* No Boolean variables, no settable Int32 variables. */
FMI3_Export fmi3Status fmi3GetBoolean(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Boolean values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetBoolean", "this FMU has no Boolean variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetBoolean(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Boolean values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetBoolean", "this FMU has no Boolean variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int32 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetInt32", "no Int32 variable is settable (the contact counts are outputs)") : fmi3OK;
}

/* A refused (Discard) step leaves the soil at the step's start, which is the last successful time. */
FMI3_Export fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint,
                                  fmi3Float64 communicationStepSize, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                  fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminateSimulation,
                                  fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime) {
    SoilStatus status = soil_step(SOIL(instance), currentCommunicationPoint, communicationStepSize);
    *eventHandlingNeeded = fmi3False;
    /* a Discard stops the soil at the step's start: an early return at the last successful time; an
     * unchanged retry of a refused step cannot succeed: terminate (the master stops there) */
    *terminateSimulation = SOIL(instance)->terminated ? fmi3True : fmi3False;
    *earlyReturn = status == SOIL_DISCARD && ((Fmu *)instance)->early_return_allowed ? fmi3True : fmi3False;
    *lastSuccessfulTime = SOIL(instance)->real[VR_TIME];
    return STATUS[status];
}

/* FMU states: the soil snapshot the server keeps (no serialization). */
FMI3_Export fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    return STATUS[soil_get_state(SOIL(instance), (SoilSnapshot **)FMUState)];
}
FMI3_Export fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState) {
    return STATUS[soil_set_state(SOIL(instance), (const SoilSnapshot *)FMUState)];
}
FMI3_Export fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    return STATUS[soil_free_state(SOIL(instance), (SoilSnapshot **)FMUState)];
}

/* Everything below is not offered by this FMU (from fmi3FunctionTypes.h): each call is an Error, logged. */
FMI3_Export fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment, fmi3LogMessageCallback logMessage) {
    if (logMessage) logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                           "fmi3InstantiateModelExchange: this FMU offers co-simulation only, not Model Exchange");
    return NULL;
}
FMI3_Export fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment, fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate, fmi3LockPreemptionCallback lockPreemption, fmi3UnlockPreemptionCallback unlockPreemption) {
    if (logMessage) logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                           "fmi3InstantiateScheduledExecution: this FMU offers co-simulation only, not Scheduled Execution");
    return NULL;
}
FMI3_Export fmi3Status fmi3EnterEventMode(fmi3Instance instance) {
    return REFUSE(instance, "fmi3EnterEventMode", "no event mode (hasEventMode is false)");
}
FMI3_Export fmi3Status fmi3GetFloat32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float32 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetFloat32", "this FMU has no Float32 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetInt8(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Int8 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetInt8", "this FMU has no Int8 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetUInt8(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt8 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetUInt8", "this FMU has no UInt8 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetInt16(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Int16 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetInt16", "this FMU has no Int16 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetUInt16(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt16 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetUInt16", "this FMU has no UInt16 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetUInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt32 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetUInt32", "this FMU has no UInt32 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetInt64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Int64 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetInt64", "this FMU has no Int64 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetUInt64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetUInt64", "this FMU has no UInt64 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, size_t valueSizes[], fmi3Binary values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3GetBinary", "this FMU has no Binary variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Clock values[]) {
    return nValueReferences ? REFUSE(instance, "fmi3GetClock", "this FMU has no Clock variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetFloat32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float32 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetFloat32", "this FMU has no Float32 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetInt8(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int8 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetInt8", "this FMU has no Int8 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetUInt8(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt8 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetUInt8", "this FMU has no UInt8 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetInt16(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int16 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetInt16", "this FMU has no Int16 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetUInt16(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt16 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetUInt16", "this FMU has no UInt16 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetUInt32(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt32 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetUInt32", "this FMU has no UInt32 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetInt64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int64 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetInt64", "this FMU has no Int64 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetUInt64(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetUInt64", "this FMU has no UInt64 variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const size_t valueSizes[], const fmi3Binary values[], size_t nValues) {
    return nValueReferences ? REFUSE(instance, "fmi3SetBinary", "this FMU has no Binary variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Clock values[]) {
    return nValueReferences ? REFUSE(instance, "fmi3SetClock", "this FMU has no Clock variable") : fmi3OK;
}
FMI3_Export fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference, size_t* nDependencies) {
    return REFUSE(instance, "fmi3GetNumberOfVariableDependencies", "no variable dependencies are offered");
}
FMI3_Export fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent, size_t elementIndicesOfDependent[], fmi3ValueReference independents[], size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[], size_t nDependencies) {
    return REFUSE(instance, "fmi3GetVariableDependencies", "no variable dependencies are offered");
}
FMI3_Export fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t* size) {
    return REFUSE(instance, "fmi3SerializedFMUStateSize", "FMU states are not serializable (canSerializeFMUState is false)");
}
FMI3_Export fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[], size_t size) {
    return REFUSE(instance, "fmi3SerializeFMUState", "FMU states are not serializable (canSerializeFMUState is false)");
}
FMI3_Export fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size, fmi3FMUState* FMUState) {
    return REFUSE(instance, "fmi3DeserializeFMUState", "FMU states are not serializable (canSerializeFMUState is false)");
}
FMI3_Export fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns, const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    return REFUSE(instance, "fmi3GetDirectionalDerivative", "no directional derivatives (providesDirectionalDerivatives is false)");
}
FMI3_Export fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns, const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    return REFUSE(instance, "fmi3GetAdjointDerivative", "no adjoint derivatives (providesAdjointDerivatives is false)");
}
FMI3_Export fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) {
    return REFUSE(instance, "fmi3EnterConfigurationMode", "no structural parameters: no configuration mode");
}
FMI3_Export fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) {
    return REFUSE(instance, "fmi3ExitConfigurationMode", "no structural parameters: no configuration mode");
}
FMI3_Export fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[]) {
    return REFUSE(instance, "fmi3GetIntervalDecimal", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[], fmi3IntervalQualifier qualifiers[]) {
    return REFUSE(instance, "fmi3GetIntervalFraction", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float64 shifts[]) {
    return REFUSE(instance, "fmi3GetShiftDecimal", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[]) {
    return REFUSE(instance, "fmi3GetShiftFraction", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float64 intervals[]) {
    return REFUSE(instance, "fmi3SetIntervalDecimal", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    return REFUSE(instance, "fmi3SetIntervalFraction", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float64 shifts[]) {
    return REFUSE(instance, "fmi3SetShiftDecimal", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    return REFUSE(instance, "fmi3SetShiftFraction", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) {
    return REFUSE(instance, "fmi3EvaluateDiscreteStates", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean* discreteStatesNeedUpdate, fmi3Boolean* terminateSimulation, fmi3Boolean* nominalsOfContinuousStatesChanged, fmi3Boolean* valuesOfContinuousStatesChanged, fmi3Boolean* nextEventTimeDefined, fmi3Float64* nextEventTime) {
    return REFUSE(instance, "fmi3UpdateDiscreteStates", "no clocks, no events: a co-simulation FMU without event mode");
}
FMI3_Export fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance) {
    return REFUSE(instance, "fmi3EnterContinuousTimeMode", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean* enterEventMode, fmi3Boolean* terminateSimulation) {
    return REFUSE(instance, "fmi3CompletedIntegratorStep", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time) {
    return REFUSE(instance, "fmi3SetTime", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 continuousStates[], size_t nContinuousStates) {
    return REFUSE(instance, "fmi3SetContinuousStates", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 derivatives[], size_t nContinuousStates) {
    return REFUSE(instance, "fmi3GetContinuousStateDerivatives", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 eventIndicators[], size_t nEventIndicators) {
    return REFUSE(instance, "fmi3GetEventIndicators", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 continuousStates[], size_t nContinuousStates) {
    return REFUSE(instance, "fmi3GetContinuousStates", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[], size_t nContinuousStates) {
    return REFUSE(instance, "fmi3GetNominalsOfContinuousStates", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t* nEventIndicators) {
    return REFUSE(instance, "fmi3GetNumberOfEventIndicators", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t* nContinuousStates) {
    return REFUSE(instance, "fmi3GetNumberOfContinuousStates", "a Model Exchange function: this FMU offers co-simulation only");
}
FMI3_Export fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int32 orders[], fmi3Float64 values[], size_t nValues) {
    return REFUSE(instance, "fmi3GetOutputDerivatives", "no output derivatives (maxOutputDerivativeOrder is 0)");
}
FMI3_Export fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference, fmi3Float64 activationTime) {
    return REFUSE(instance, "fmi3ActivateModelPartition", "no clocks, no events: a co-simulation FMU without event mode");
}
