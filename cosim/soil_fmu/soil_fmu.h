/* The soil FMU's front end: what the FMI 2.0 layer (fmi2.c) and the FMI 3.0 layer (fmi3.c) share.
 *
 * The front end links no Python. When initialization ends it starts the soil server
 * (the module cosim.soil_fmu.server run by `PYTHON -E`, a process of its own), talks to it over a
 * socket pair and forwards each doStep's wheel kinematics; the server answers with the
 * wheel wrenches. Protocol, variables and run-time needs: docs/fmu.md.
 */
#ifndef SOIL_FMU_H
#define SOIL_FMU_H

#include <stddef.h>
#include <sys/types.h>

/* Value references, the same in both FMI versions (modelDescription.xml lists them). */
enum {
    VR_TIME = 0,          /* FMI 3.0 independent variable [s] */
    VR_DEM_STEP = 1,      /* parameter [s] */
    VR_GRAVITY = 2,       /* parameters 2, 3, 4: gravity.x, .y, .z [m/s2] */
    VR_START_TIMEOUT = 5, /* parameter [s]: longest wait for the server to start */
    VR_STEP_TIMEOUT = 6,  /* parameter [s]: longest wait for one doStep's answer */
    VR_REAL_PARAMETERS = 7,
    VR_PYTHON = 7,        /* String parameter: the server's Python ("" = default) */
    VR_DEVICE = 8,        /* String parameter: the server's Warp device ("" = default) */
    VR_WHEEL = 100,       /* wheel i's variables start at VR_WHEEL * (i + 1) */
};

/* Offsets of one wheel's variables (wheel i: VR_WHEEL * (i + 1) + offset). */
enum {
    W_POSITION = 0,          /* inputs: position x y z [m] */
    W_ORIENTATION = 3,       /* quaternion w x y z [1] */
    W_VELOCITY = 7,          /* x y z [m/s] */
    W_ANGULAR_VELOCITY = 10, /* x y z [rad/s] */
    W_INPUTS = 13,           /* number of inputs per wheel */
    W_FORCE = 13,            /* outputs: mean force x y z over the step [N] */
    W_TORQUE = 16,           /* mean torque about the hub x y z [N.m] */
    W_FORCE_END = 19,        /* force at the step's end [N] */
    W_TORQUE_END = 22,       /* torque at the step's end [N.m] */
    W_SINKAGE = 25,          /* [m] */
    W_WORK = 26,             /* work done on the soil during the step [J] */
    W_CONTACTS = 27,         /* contact count (Integer / Int32) */
    W_SIZE = 28,
    W_OUTPUTS = W_SIZE - W_INPUTS,
};

typedef enum { SOIL_OK, SOIL_WARNING, SOIL_DISCARD, SOIL_ERROR } SoilStatus;

/* The FMI layer's logger: message is plain text (the layer escapes it if it must). */
typedef void (*SoilLogger)(void *environment, SoilStatus status, const char *category, const char *message);

typedef struct {
    char *instance_name;
    char *resources;       /* the FMU's resources folder, ending in '/' */
    int wheel_count;
    SoilLogger logger;
    void *log_environment;
    int debug;             /* log the server's messages and progress (loggingOn) */

    double real[VR_REAL_PARAMETERS]; /* time and the Float64 parameters, by value reference */
    double real_start[VR_REAL_PARAMETERS];
    char *python, *device;           /* String parameters */
    char *default_python;            /* from resources/frontend.txt */
    double *wheel, *wheel_start;     /* wheel_count * W_SIZE values */

    int initialized;       /* the server runs and holds the soil */
    int stopped;           /* terminated by the master (soil_stop after a start): a step needs a reset first */
    int failed;            /* the server failed: every call until reset is an error */
    int in_error;          /* an Error was returned: FMI then allows an FMU state restored, reset or free only */
    pid_t pid;             /* the server process, 0 when none */
    int socket;            /* our end of the socket pair, -1 when none */
    int errors;            /* read end of the server's stderr pipe, -1 when none */
    char line[512];        /* the server's stderr line being read */
    size_t line_length;
    char tail[2048];       /* the server's last stderr lines, for error messages */

    int discards;          /* Discards in a row from the same time (0 after a successful step) */
    double discarded_step; /* the size of the last discarded step [s] */
    unsigned long long discarded_inputs; /* a hash of the wheel inputs of the last discarded step */
    unsigned long long serial; /* this instance's own number: an FMU state belongs to one instance (see owner) */
    int terminated;        /* a step was retried unchanged after its Discard: it cannot succeed (fmi2Terminated) */
    unsigned generation;   /* counts the servers started: an FMU state belongs to one */
    unsigned next_state;   /* the id of the next FMU state the server keeps */
} Soil;

/* An FMU state (fmi2GetFMUstate / fmi3GetFMUState): the soil snapshot the server keeps under `id`, and
 * the front end's own values (time, parameters, wheel inputs and outputs) at that moment. */
typedef struct {
    unsigned id, generation;
    const void *owner;     /* the instance that took it: its address (unique among live instances, whatever */
    unsigned long long serial; /* copy of the library each was loaded from) and its serial (an address reused) */
    double real[VR_REAL_PARAMETERS];
    double *wheel;
    int discards, terminated;
    double discarded_step;
    unsigned long long discarded_inputs;
} SoilSnapshot;

/* Read resources/frontend.txt; NULL (and a logged error) if it is missing or belongs to another FMU. */
Soil *soil_new(const char *instance_name, const char *resources, const char *token, SoilLogger logger,
               void *log_environment, int logging_on);
void soil_free(Soil *soil);

SoilStatus soil_start(Soil *soil);                      /* end of initialization: start the server */
SoilStatus soil_step(Soil *soil, double time, double step);
void soil_stop(Soil *soil);                             /* stop the server (terminate) */
void soil_reset(Soil *soil);                            /* stop the server, restore the start values */

SoilStatus soil_get_real(Soil *soil, unsigned vr, double *value);
SoilStatus soil_set_real(Soil *soil, unsigned vr, double value);
SoilStatus soil_get_integer(Soil *soil, unsigned vr, int *value);
SoilStatus soil_get_string(Soil *soil, unsigned vr, const char **value);
SoilStatus soil_set_string(Soil *soil, unsigned vr, const char *value);

/* FMU states: *state NULL: a new one; else it is overwritten. Valid while the server that took it runs. */
SoilStatus soil_get_state(Soil *soil, SoilSnapshot **state);
SoilStatus soil_set_state(Soil *soil, const SoilSnapshot *state);
SoilStatus soil_free_state(Soil *soil, SoilSnapshot **state);

void soil_log(Soil *soil, SoilStatus status, const char *category, const char *format, ...);
/* A call the FMU does not offer, or whose arguments it cannot take: logged as an Error naming the call
   (the instance then is in FMI's Error state, like after any other Error). */
SoilStatus soil_refuse(Soil *soil, const char *call, const char *why);

#endif
