/* The soil FMU's front end, shared by both FMI versions (see soil_fmu.h and docs/fmu.md).
 *
 * Failure is a status, never a hang or a signal: every wait on the server has a deadline,
 * writes never raise SIGPIPE, and a server that dies, hangs or cannot start is reported
 * with its exit status and its last stderr lines, then killed and reaped.
 */
#define _GNU_SOURCE
#include "soil_fmu.h"

#include <ctype.h>
#include <errno.h>
#include <fcntl.h>
#include <locale.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
#ifdef __APPLE__
#include <xlocale.h>
#endif

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "the soil server protocol is little-endian"
#endif
#ifndef MSG_NOSIGNAL
#define MSG_NOSIGNAL 0 /* macOS: SO_NOSIGPIPE is set on the socket instead */
#endif

extern char **environ;

/* Protocol (docs/fmu.md): frames of uint32 kind, uint32 payload length, payload. */
enum { PROTOCOL_VERSION = 2 };
enum { MSG_INIT = 1, MSG_PLACE = 2, MSG_STEP = 3, MSG_BYE = 4, MSG_SAVE = 5, MSG_RESTORE = 6, MSG_FREE = 7,
       MSG_OK = 10, MSG_OUTPUTS = 11, MSG_DISCARD = 12, MSG_ERROR = 13 };

#define SERVER_MODULE "cosim.soil_fmu.server"
/* `python -m` would put the importer's working directory first on sys.path, where a folder
   named soil/ or cosim/ would hide the package: start the module without it. */
#define SERVER_CODE "import runpy, sys; sys.path.remove(''); runpy.run_module('" SERVER_MODULE "', " \
                    "run_name='__main__', alter_sys=True)"
#define STOP_WAIT 5.0 /* [s] a stopping server gets this long before it is killed */
#define MAX_STEP_COUNT 1e10 /* most DEM (or SCM) steps in one doStep: beyond, the step never ends */

/* ---------------------------------------------------------------------------- logging */

/* After an Error FMI lets a master restore an FMU state taken before it, reset or free the instance, and
   nothing else: a master that set a refused input and stepped on would step on the input's old value. */
static int refused_after_error(Soil *s, const char *call) {
    if (!s->in_error) return 0;
    soil_log(s, SOIL_ERROR, "logStatusError", "%s after an Error: restore an FMU state taken before it "
             "(fmi2SetFMUstate / fmi3SetFMUState), or reset or free the instance", call);
    return 1;
}

void soil_log(Soil *s, SoilStatus status, const char *category, const char *format, ...) {
    char message[4096];
    va_list args;
    if (status == SOIL_ERROR) s->in_error = 1; /* every Error is logged, so this marks each one */
    if (!s->logger || (status == SOIL_OK && !s->debug)) return;
    va_start(args, format);
    vsnprintf(message, sizeof message, format, args);
    va_end(args);
    s->logger(s->log_environment, status, category, message);
}

SoilStatus soil_refuse(Soil *s, const char *call, const char *why) {
    if (s) soil_log(s, SOIL_ERROR, "logStatusError", "%s: %s", call, why);
    return SOIL_ERROR;
}

static char *copy_text(const char *text) {
    char *copy = malloc(strlen(text) + 1);
    if (copy) strcpy(copy, text);
    return copy;
}

/* ---------------------------------------------------------------------------- start values */

/* A whole number of digits at `text` (no sign, no overflow, at most `limit`), then a space or the line's
   end: its end, or NULL. sscanf's %u would wrap 4294967396 to 100. */
static const char *parse_whole(const char *text, unsigned long limit, unsigned long *value) {
    char *end;
    if (!isdigit((unsigned char)*text)) return NULL;
    errno = 0;
    *value = strtoul(text, &end, 10);
    if (errno == ERANGE || *value > limit || (*end && *end != ' ')) return NULL;
    return end;
}

/* "real VR VALUE": a value reference and a finite number filling the rest of the line. */
static int parse_real(const char *line, unsigned *vr, double *value) {
    unsigned long reference;
    char *end;
    const char *rest = parse_whole(line + 5, 0xFFFFFFFFul, &reference);
    if (!rest || *rest != ' ' || rest[1] == 0 || isspace((unsigned char)rest[1])) return 0;
    errno = 0;
    *value = strtod(rest + 1, &end);
    *vr = (unsigned)reference;
    return *end == 0 && errno != ERANGE && isfinite(*value);
}

/* resources/frontend.txt, written at export: "token T", "wheels N", "python P", "real VR VALUE". Numbers
   are read in the C locale: a host program's decimal comma must not turn 0.001 into 0. */
static int read_frontend(Soil *s, const char *token) {
    char path[4096], line[4096];
    FILE *file;
    int token_ok = 0, failed = 0;
    locale_t numbers = newlocale(LC_NUMERIC_MASK, "C", (locale_t)0), previous;
    snprintf(path, sizeof path, "%sfrontend.txt", s->resources);
    file = fopen(path, "r");
    if (!file || !numbers) {
        if (!file)
            soil_log(s, SOIL_ERROR, "logStatusError", "cannot read %s: %s (is the resource folder right?)", path,
                     strerror(errno));
        else
            soil_log(s, SOIL_ERROR, "logStatusError", "cannot make the C locale to read %s: %s", path,
                     strerror(errno));
        if (file) fclose(file);
        if (numbers) freelocale(numbers);
        return -1;
    }
    previous = uselocale(numbers);
    for (int number = 1; fgets(line, sizeof line, file); number++) {
        unsigned vr = 0;
        unsigned long count = 0;
        double value = 0.0;
        size_t length = strcspn(line, "\r\n");
        while (length > 0 && isspace((unsigned char)line[length - 1])) length--; /* an editor's trailing blanks */
        line[length] = 0;
        int real = strncmp(line, "real ", 5) == 0 && parse_real(line, &vr, &value);
        if (strncmp(line, "wheels ", 7) == 0) {
            const char *end = parse_whole(line + 7, 10000, &count);
            if (!end || *end) count = 0;
        }
        if (strncmp(line, "token ", 6) == 0) {
            token_ok = token == NULL || strcmp(line + 6, token) == 0;
        } else if (count > 0 && !s->wheel) {
            s->wheel_count = (int)count;
            s->wheel = calloc((size_t)count * W_SIZE, sizeof(double));
            s->wheel_start = calloc((size_t)count * W_SIZE, sizeof(double));
            if (!s->wheel || !s->wheel_start) break;
        } else if (strncmp(line, "python ", 7) == 0) {
            free(s->default_python);
            s->default_python = copy_text(line + 7);
        } else if (real && vr < VR_REAL_PARAMETERS) {
            s->real_start[vr] = value;
        } else if (real && s->wheel && vr >= VR_WHEEL && vr / VR_WHEEL <= (unsigned)s->wheel_count
                   && vr % VR_WHEEL < W_SIZE) {
            s->wheel_start[(vr / VR_WHEEL - 1) * W_SIZE + vr % VR_WHEEL] = value;
        } else if (line[0] && line[0] != '#') { /* an edited or damaged file: a value read as 0 would be
                                                   blamed on a parameter */
            soil_log(s, SOIL_ERROR, "logStatusError", "%s line %d is not one of '# comment', 'token T', "
                     "'wheels N' (once, 1 .. 10000), 'python P', 'real VR VALUE' (a finite value of a known "
                     "variable): %.200s", path, number, line);
            failed = 1;
            break;
        }
    }
    uselocale(previous);
    freelocale(numbers);
    fclose(file);
    if (failed) return -1;
    if (!s->wheel || !s->wheel_start || !s->default_python) {
        soil_log(s, SOIL_ERROR, "logStatusError", "%s is incomplete (wheels, python)", path);
        return -1;
    }
    if (!token_ok) {
        soil_log(s, SOIL_ERROR, "logStatusError", "the instantiation token / GUID '%s' is not the one in %s: "
                 "the binary and the resources belong to different FMUs", token ? token : "", path);
        return -1;
    }
    return 0;
}

static void restore_start_values(Soil *s) {
    memcpy(s->real, s->real_start, sizeof s->real);
    memcpy(s->wheel, s->wheel_start, (size_t)s->wheel_count * W_SIZE * sizeof(double));
    free(s->python);
    free(s->device);
    s->python = copy_text("");
    s->device = copy_text("");
}

Soil *soil_new(const char *instance_name, const char *resources, const char *token, SoilLogger logger,
               void *log_environment, int logging_on) {
    Soil *s = calloc(1, sizeof(Soil));
    size_t length;
    static unsigned long long instances = 0; /* instances made by this copy of the library */
    if (!s) return NULL;
    s->serial = __atomic_add_fetch(&instances, 1, __ATOMIC_RELAXED);
    s->logger = logger;
    s->log_environment = log_environment;
    s->debug = logging_on;
    s->socket = s->errors = -1;
    s->instance_name = copy_text(instance_name ? instance_name : "soil");
    for (char *c = s->instance_name; c && *c; c++)
        if (*c == '\n' || *c == '\r') *c = ' '; /* the name travels in a line of the INIT message */
    if (!resources || !*resources) {
        soil_log(s, SOIL_ERROR, "logStatusError", "no resource folder given: the soil FMU needs its resources");
        soil_free(s);
        return NULL;
    }
    length = strlen(resources);
    s->resources = malloc(length + 2);
    if (!s->resources || !s->instance_name) {
        soil_free(s);
        return NULL;
    }
    strcpy(s->resources, resources);
    if (resources[length - 1] != '/') strcat(s->resources, "/");
    if (read_frontend(s, token) != 0) {
        soil_free(s);
        return NULL;
    }
    restore_start_values(s);
    return s;
}

/* ---------------------------------------------------------------------------- the server's stderr */

static void remember(Soil *s, const char *line) {
    size_t keep = sizeof s->tail - 1, have = strlen(s->tail), add = strlen(line) + 1;
    if (add > keep) {
        line += add - keep;
        add = keep;
    }
    if (have + add > keep) { /* drop the oldest text */
        memmove(s->tail, s->tail + (have + add - keep), keep - add);
        have = keep - add;
    }
    memcpy(s->tail + have, line, add - 1);
    s->tail[have + add - 1] = '\n';
    s->tail[have + add] = 0;
}

/* A server line "warning: ..." is logged as a warning; the rest only with logging on. */
static void server_line(Soil *s) {
    s->line[s->line_length] = 0;
    s->line_length = 0;
    if (!s->line[0]) return;
    remember(s, s->line);
    if (strncmp(s->line, "warning: ", 9) == 0)
        soil_log(s, SOIL_WARNING, "logServer", "soil server: %s", s->line + 9);
    else
        soil_log(s, SOIL_OK, "logServer", "soil server: %s", s->line);
}

static void drain_errors(Soil *s) {
    char buffer[1024];
    ssize_t n;
    while (s->errors >= 0) {
        n = read(s->errors, buffer, sizeof buffer);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) {
            if (n == 0) { /* the server closed its stderr */
                close(s->errors);
                s->errors = -1;
                if (s->line_length) server_line(s);
            }
            return;
        }
        for (ssize_t i = 0; i < n; i++) {
            if (buffer[i] == '\n' || s->line_length == sizeof s->line - 1) server_line(s);
            if (buffer[i] != '\n') s->line[s->line_length++] = buffer[i];
        }
    }
}

/* ---------------------------------------------------------------------------- the server process */

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

static void pause_briefly(void) {
    struct timespec t = {0, 10 * 1000 * 1000};
    nanosleep(&t, NULL);
}

/* Wait up to `seconds` for the server to exit; describe how it ended in `how`. 1: it has. */
static int reap(Soil *s, double seconds, char *how, size_t size) {
    double deadline = now() + seconds;
    int status;
    for (;;) {
        pid_t r = waitpid(s->pid, &status, WNOHANG);
        if (r == s->pid) {
            if (WIFSIGNALED(status))
                snprintf(how, size, "was killed by signal %d (%s)", WTERMSIG(status), strsignal(WTERMSIG(status)));
            else
                snprintf(how, size, "exited with status %d", WEXITSTATUS(status));
            s->pid = 0;
            return 1;
        }
        if (r < 0 && errno != EINTR) { /* not our child any more (e.g. SIGCHLD ignored by the importer) */
            snprintf(how, size, "ended (exit status unknown: %s)", strerror(errno));
            s->pid = 0;
            return 1;
        }
        if (now() > deadline) {
            snprintf(how, size, "is still running");
            return 0;
        }
        pause_briefly();
    }
}

static void close_channel(Soil *s) {
    if (s->socket >= 0) close(s->socket);
    s->socket = -1;
}

/* Kill the server if it still runs and forget it; no process or descriptor is left. */
static void kill_server(Soil *s) {
    char how[128];
    close_channel(s);
    if (s->pid > 0) {
        kill(s->pid, SIGKILL);
        if (!reap(s, STOP_WAIT, how, sizeof how))
            soil_log(s, SOIL_WARNING, "logStatusWarning", "soil server (pid %d) %s after SIGKILL", (int)s->pid, how);
        s->pid = 0;
    }
    drain_errors(s);
    if (s->errors >= 0) close(s->errors);
    s->errors = -1;
}

/* The server failed: log why (with its last stderr lines), make sure it is gone, refuse further steps. */
static SoilStatus server_failed(Soil *s, const char *format, ...) {
    char message[2048];
    va_list args;
    va_start(args, format);
    vsnprintf(message, sizeof message, format, args);
    va_end(args);
    kill_server(s);
    s->failed = 1;
    s->initialized = 0;
    if (s->tail[0])
        soil_log(s, SOIL_ERROR, "logStatusError", "%s\nthe soil server's last messages:\n%s", message, s->tail);
    else
        soil_log(s, SOIL_ERROR, "logStatusError", "%s", message);
    return SOIL_ERROR;
}

static const char *python_of(const Soil *s) {
    const char *python = getenv("REGOLITH_SOIL_PYTHON");
    if (s->python && *s->python) return s->python;
    if (python && *python) return python;
    return s->default_python;
}

/* The socket reached end of file: the server ended; say how. */
static SoilStatus server_gone(Soil *s, const char *doing) {
    char how[128];
    int pid = (int)s->pid;
    close_channel(s);
    reap(s, 1.0, how, sizeof how);
    drain_errors(s);
    if (!s->initialized && !s->tail[0]) /* it said nothing: the Python itself is the likely cause */
        return server_failed(s, "the soil server (pid %d) %s while %s, saying nothing: is %s (the python "
                             "parameter, else $REGOLITH_SOIL_PYTHON, else the exporting Python) a Python with "
                             "regolith-cosim?", pid, how, doing, python_of(s));
    return server_failed(s, "the soil server (pid %d) %s while %s", pid, how, doing);
}

/* A descriptor that is not 0..9, so that the child's fixed numbers (0, 1, 2, 3) cannot collide with it. */
static int high_descriptor(int fd) {
    int high;
    if (fd >= 10) return fd;
    high = fcntl(fd, F_DUPFD_CLOEXEC, 10);
    close(fd);
    return high;
}

static SoilStatus spawn_server(Soil *s) {
    int pair[2], err[2];
    posix_spawn_file_actions_t actions;
    const char *python = python_of(s);
    char *argv[] = {(char *)python, "-E", "-c", SERVER_CODE, "--fd", "3", NULL};
    pid_t pid;
    int error;

    s->tail[0] = 0;
    s->line_length = 0;
#ifdef SOCK_CLOEXEC
    if (socketpair(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0, pair) != 0)
#else
    if (socketpair(AF_UNIX, SOCK_STREAM, 0, pair) != 0)
#endif
        return server_failed(s, "cannot create the socket pair for the soil server: %s", strerror(errno));
#ifdef __linux__
    if (pipe2(err, O_CLOEXEC) != 0) {
#else
    if (pipe(err) != 0) {
#endif
        close(pair[0]);
        close(pair[1]);
        return server_failed(s, "cannot create the soil server's stderr pipe: %s", strerror(errno));
    }
    /* our ends must not leak into other children of the importer */
    pair[0] = high_descriptor(pair[0]);
    pair[1] = high_descriptor(pair[1]);
    err[0] = high_descriptor(err[0]);
    err[1] = high_descriptor(err[1]);
    if (pair[0] < 0 || pair[1] < 0 || err[0] < 0 || err[1] < 0) {
        for (int i = 0; i < 2; i++) {
            if (pair[i] >= 0) close(pair[i]);
            if (err[i] >= 0) close(err[i]);
        }
        return server_failed(s, "no file descriptor left for the soil server's channel: %s", strerror(errno));
    }
    fcntl(pair[0], F_SETFD, FD_CLOEXEC);
    fcntl(pair[1], F_SETFD, FD_CLOEXEC);
    fcntl(err[0], F_SETFD, FD_CLOEXEC);
    fcntl(err[1], F_SETFD, FD_CLOEXEC);
#ifdef SO_NOSIGPIPE
    { int on = 1; setsockopt(pair[0], SOL_SOCKET, SO_NOSIGPIPE, &on, sizeof on); }
#endif
    /* the child: stdin and stdout /dev/null (nothing reaches the importer's stdout), stderr the pipe,
       descriptor 3 its end of the socket pair (dup2 clears close-on-exec) */
    posix_spawn_file_actions_init(&actions);
    posix_spawn_file_actions_addopen(&actions, 0, "/dev/null", O_RDONLY, 0);
    posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
    posix_spawn_file_actions_adddup2(&actions, err[1], 2);
    posix_spawn_file_actions_adddup2(&actions, pair[1], 3);
    error = posix_spawnp(&pid, python, &actions, NULL, argv, environ);
    posix_spawn_file_actions_destroy(&actions);
    close(pair[1]);
    close(err[1]);
    if (error != 0) {
        close(pair[0]);
        close(err[0]);
        return server_failed(s, "cannot start the soil server (%s -E, module %s): %s (set the parameter 'python' "
                             "or REGOLITH_SOIL_PYTHON to a Python that has regolith-cosim installed)",
                             python, SERVER_MODULE, strerror(error));
    }
    s->pid = pid;
    s->socket = pair[0];
    s->errors = err[0];
    fcntl(s->socket, F_SETFL, fcntl(s->socket, F_GETFL) | O_NONBLOCK);
    fcntl(s->errors, F_SETFL, fcntl(s->errors, F_GETFL) | O_NONBLOCK);
    soil_log(s, SOIL_OK, "logEvents", "started the soil server: pid %d, %s -E, module %s", (int)pid, python,
             SERVER_MODULE);
    return SOIL_OK;
}

/* ---------------------------------------------------------------------------- messages */

/* Wait until the socket is ready for `events` (reading the server's stderr meanwhile).
   1: ready, 0: deadline passed, -1: poll failed. */
static int wait_socket(Soil *s, short events, double deadline) {
    for (;;) {
        struct pollfd fds[2] = {{s->socket, events, 0}, {s->errors, POLLIN, 0}};
        double left = deadline - now();
        int n;
        if (left <= 0) return 0;
        n = poll(fds, s->errors >= 0 ? 2 : 1, left > 3600.0 ? 3600000 : (int)ceil(left * 1000.0));
        if (n < 0 && errno == EINTR) continue;
        if (n < 0) return -1;
        if (s->errors >= 0 && fds[1].revents) drain_errors(s);
        if (fds[0].revents) return 1;
    }
}

/* 0: sent; otherwise the server failed (logged). */
static SoilStatus send_message(Soil *s, uint32_t kind, const void *payload, uint32_t length, double timeout,
                               const char *doing) {
    uint32_t header[2] = {kind, length};
    const char *parts[2] = {(const char *)header, (const char *)payload};
    size_t sizes[2] = {sizeof header, length};
    double deadline = now() + timeout;
    for (int p = 0; p < 2; p++) {
        size_t done = 0;
        while (done < sizes[p]) {
            ssize_t n = send(s->socket, parts[p] + done, sizes[p] - done, MSG_NOSIGNAL);
            if (n > 0) {
                done += (size_t)n;
            } else if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) {
                int ready = wait_socket(s, POLLOUT, deadline);
                if (ready == 0)
                    return server_failed(s, "the soil server (pid %d) did not take a message within %g s while %s",
                                         (int)s->pid, timeout, doing);
                if (ready < 0) return server_failed(s, "poll failed: %s", strerror(errno));
            } else {
                return server_gone(s, doing);
            }
        }
    }
    return SOIL_OK;
}

static SoilStatus receive_bytes(Soil *s, void *buffer, size_t size, double deadline, double timeout,
                                const char *timeout_name, const char *doing) {
    size_t done = 0;
    while (done < size) {
        ssize_t n = recv(s->socket, (char *)buffer + done, size - done, 0);
        if (n > 0) {
            done += (size_t)n;
        } else if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) {
            int ready = wait_socket(s, POLLIN, deadline);
            if (ready == 0)
                return server_failed(s, "the soil server (pid %d) did not answer within %g s%s%s%s while %s; it "
                                     "was killed", (int)s->pid, timeout, timeout_name ? " (parameter " : "",
                                     timeout_name ? timeout_name : "", timeout_name ? ")" : "", doing);
            if (ready < 0) return server_failed(s, "poll failed: %s", strerror(errno));
        } else {
            return server_gone(s, doing);
        }
    }
    return SOIL_OK;
}

/* Receive one message; *payload is malloc'ed and 0-terminated (the caller frees it). */
static SoilStatus receive_message(Soil *s, uint32_t *kind, char **payload, uint32_t *length, double timeout,
                                  const char *timeout_name, const char *doing) {
    uint32_t header[2];
    double deadline = now() + timeout;
    *payload = NULL;
    if (receive_bytes(s, header, sizeof header, deadline, timeout, timeout_name, doing) != SOIL_OK)
        return SOIL_ERROR;
    if (header[1] > (1u << 30))
        return server_failed(s, "the soil server sent a malformed message (length %u) while %s", header[1], doing);
    *payload = malloc((size_t)header[1] + 1);
    if (!*payload) return server_failed(s, "out of memory");
    if (receive_bytes(s, *payload, header[1], deadline, timeout, timeout_name, doing) != SOIL_OK) {
        free(*payload);
        *payload = NULL;
        return SOIL_ERROR;
    }
    (*payload)[header[1]] = 0;
    *kind = header[0];
    *length = header[1];
    return SOIL_OK;
}

/* Send a request and take the answer: outputs are stored, OK text is logged; DISCARD and ERROR are statuses. */
static SoilStatus request(Soil *s, uint32_t kind, const void *payload, uint32_t length, double timeout,
                          const char *timeout_name, const char *doing) {
    uint32_t answer, size;
    char *text;
    SoilStatus status;
    if (send_message(s, kind, payload, length, timeout, doing) != SOIL_OK) return SOIL_ERROR;
    if (receive_message(s, &answer, &text, &size, timeout, timeout_name, doing) != SOIL_OK) return SOIL_ERROR;
    status = SOIL_OK;
    if (answer == MSG_OUTPUTS && size == (uint32_t)(s->wheel_count * W_OUTPUTS * sizeof(double))) {
        const double *values = (const double *)text;
        for (int i = 0; i < s->wheel_count; i++)
            memcpy(s->wheel + i * W_SIZE + W_INPUTS, values + i * W_OUTPUTS, W_OUTPUTS * sizeof(double));
    } else if (answer == MSG_OK) {
        soil_log(s, SOIL_OK, "logEvents", "soil server: %s", text);
    } else if (answer == MSG_DISCARD) {
        soil_log(s, SOIL_DISCARD, "logStatusDiscard", "%s", text);
        status = SOIL_DISCARD;
    } else if (answer == MSG_ERROR) {
        soil_log(s, SOIL_ERROR, "logStatusError", "soil server error while %s: %s", doing, text);
        s->failed = 1;
        status = SOIL_ERROR;
    } else {
        status = server_failed(s, "the soil server sent an unexpected message (kind %u, %u bytes) while %s", answer,
                               size, doing);
    }
    free(text);
    return status;
}

/* FNV-1a over the step's wheel inputs (values[1..]): whether a retried step changed them. */
static unsigned long long inputs_hash(const double *values, size_t count) {
    const unsigned char *bytes = (const unsigned char *)(values + 1);
    unsigned long long hash = 1469598103934665603ULL;
    for (size_t i = 0; i < count * sizeof(double); i++) hash = (hash ^ bytes[i]) * 1099511628211ULL;
    return hash;
}

static double *inputs(const Soil *s) {
    double *values = malloc((size_t)s->wheel_count * W_INPUTS * sizeof(double) + sizeof(double));
    if (!values) return NULL;
    for (int i = 0; i < s->wheel_count; i++)
        memcpy(values + 1 + i * W_INPUTS, s->wheel + i * W_SIZE, W_INPUTS * sizeof(double));
    return values; /* values[0] is for the caller */
}

/* ---------------------------------------------------------------------------- life cycle */

/* Each wheel's orientation input must be a unit quaternion: refused here, the instance left as it was,
   rather than by the server, whose error ends the instance. */
static SoilStatus check_orientations(Soil *s) {
    for (int i = 0; i < s->wheel_count; i++) {
        const double *q = s->wheel + i * W_SIZE + W_ORIENTATION;
        double norm = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        if (!(norm > 0.5 && norm < 2.0)) {
            soil_log(s, SOIL_ERROR, "logStatusError", "input wheel_%d.orientation must be a unit quaternion "
                     "(w, x, y, z), got (%g, %g, %g, %g): %s", i, q[0], q[1], q[2], q[3],
                     s->initialized ? "restore an FMU state taken before (or reset), set a rotation and step again"
                                    : "reset the instance, set a rotation and end the initialization again");
            return SOIL_ERROR;
        }
    }
    return SOIL_OK;
}

SoilStatus soil_start(Soil *s) {
    char init[8192];
    locale_t numbers, previous;
    const char *device = s->device ? s->device : ""; /* empty: the server's $REGOLITH_SOIL_DEVICE, else the scene's */
    double *values;
    uint32_t size = (uint32_t)((size_t)s->wheel_count * W_INPUTS * sizeof(double));
    SoilStatus status;
    if (s->initialized) return SOIL_OK;
    if (s->failed) {
        soil_log(s, SOIL_ERROR, "logStatusError", "the soil server failed before; reset or free the instance");
        return SOIL_ERROR;
    }
    if (refused_after_error(s, "the end of initialization")) return SOIL_ERROR;
    if (strchr(device, '\n') || strchr(s->resources, '\n'))
        return server_failed(s, "the device name and the resource path must not contain a line break");
    if (check_orientations(s) != SOIL_OK) return SOIL_ERROR;
    if (spawn_server(s) != SOIL_OK) return SOIL_ERROR;
    numbers = newlocale(LC_NUMERIC_MASK, "C", (locale_t)0); /* the server reads 0.001, not a host's 0,001 */
    previous = numbers ? uselocale(numbers) : (locale_t)0;
    snprintf(init, sizeof init,
             "protocol %d\ninstance %s\nresources %s\nwheels %d\ndem_step %.17g\ngravity %.17g %.17g %.17g\n"
             "device %s\n",
             PROTOCOL_VERSION, s->instance_name, s->resources, s->wheel_count, s->real[VR_DEM_STEP],
             s->real[VR_GRAVITY], s->real[VR_GRAVITY + 1], s->real[VR_GRAVITY + 2], device);
    if (numbers) {
        uselocale(previous);
        freelocale(numbers);
    }
    status = request(s, MSG_INIT, init, (uint32_t)strlen(init), s->real[VR_START_TIMEOUT], "server_start_timeout",
                     "starting (loading the soil: a DEM bed and its kernels, or an SCM grid)");
    if (status != SOIL_OK) return SOIL_ERROR;
    values = inputs(s);
    if (!values) return server_failed(s, "out of memory");
    status = request(s, MSG_PLACE, values + 1, size, s->real[VR_STEP_TIMEOUT], "server_step_timeout",
                     "placing the wheels");
    free(values);
    if (status != SOIL_OK) return SOIL_ERROR;
    s->initialized = 1;
    s->stopped = 0;
    s->generation++;
    s->discards = s->terminated = 0;
    return SOIL_OK;
}

SoilStatus soil_step(Soil *s, double time, double step) {
    double *values;
    double tolerance = 1e-9 * fabs(time) + 1e-6 * step;
    unsigned long long hash;
    SoilStatus status;
    char doing[128];
    if (s->failed) {
        soil_log(s, SOIL_ERROR, "logStatusError", "the soil server failed before; reset or free the instance");
        return SOIL_ERROR;
    }
    if (refused_after_error(s, "doStep")) return SOIL_ERROR;
    if (!s->initialized) {
        soil_log(s, SOIL_ERROR, "logStatusError",
                 s->stopped ? "doStep after terminate: the instance is terminated; reset it (a new run) or free it"
                            : "doStep before the end of initialization");
        return SOIL_ERROR;
    }
    if (!(step > 0) || !isfinite(step)) {
        soil_log(s, SOIL_ERROR, "logStatusError", "communicationStepSize must be > 0 [s], got %g", step);
        return SOIL_ERROR;
    }
    if (!isfinite(time)) {
        soil_log(s, SOIL_ERROR, "logStatusError", "currentCommunicationPoint must be finite [s], got %g; the soil "
                 "is at t = %.17g s", time, s->real[VR_TIME]);
        return SOIL_ERROR;
    }
    if (step / s->real[VR_DEM_STEP] > MAX_STEP_COUNT) {
        soil_log(s, SOIL_ERROR, "logStatusError", "communicationStepSize %g s is %.3g DEM steps of dem_step %g s, "
                 "more than %.0e: it would not end; restore an FMU state taken before and give a shorter step",
                 step, step / s->real[VR_DEM_STEP], s->real[VR_DEM_STEP], MAX_STEP_COUNT);
        return SOIL_ERROR;
    }
    if (check_orientations(s) != SOIL_OK) return SOIL_ERROR;
    if (time > s->real[VR_TIME] + tolerance) {
        soil_log(s, SOIL_ERROR, "logStatusError", "doStep from t = %.17g s, but the soil is at t = %.17g s, "
                 "earlier: %s", time, s->real[VR_TIME],
                 s->discards ? "its last step was discarded, so the next one must start at the last successful "
                 "time (fmi2GetRealStatus(fmi2LastSuccessfulTime), FMI 3: lastSuccessfulTime), with a shorter "
                 "step or after restoring an FMU state" : "the soil cannot skip time");
        return SOIL_ERROR;
    }
    if (time < s->real[VR_TIME] - tolerance) {
        soil_log(s, SOIL_ERROR, "logStatusError", "doStep from t = %.17g s, but the soil is at t = %.17g s, "
                 "later: the soil goes back in time only by restoring an FMU state taken then "
                 "(canGetAndSetFMUstate: fmi2SetFMUstate / fmi3SetFMUState)", time, s->real[VR_TIME]);
        return SOIL_ERROR;
    }
    values = inputs(s);
    if (!values) return server_failed(s, "out of memory");
    values[0] = step;
    hash = inputs_hash(values, (size_t)s->wheel_count * W_INPUTS);
    snprintf(doing, sizeof doing, "stepping from t = %.9g s by %.9g s", time, step);
    status = request(s, MSG_STEP, values, (uint32_t)((size_t)(s->wheel_count * W_INPUTS + 1) * sizeof(double)),
                     s->real[VR_STEP_TIMEOUT], "server_step_timeout", doing);
    free(values);
    if (status == SOIL_OK) {
        s->real[VR_TIME] = time + step;
        s->discards = 0;
        s->terminated = 0;
    } else if (status == SOIL_DISCARD) {
        /* the soil is deterministic: the same step with the same inputs from the same state is refused again */
        if (s->discards > 0 && step >= s->discarded_step * (1 - 1e-12) && hash == s->discarded_inputs) {
            s->terminated = 1;
            soil_log(s, SOIL_DISCARD, "logStatusDiscard", "the step from t = %.9g s was retried unchanged after "
                     "its Discard (as long, with the same wheel inputs) and was refused again: terminating "
                     "(fmi2Terminated); retry with a shorter step or other wheel motion instead", time);
        } else {
            soil_log(s, SOIL_DISCARD, "logStatusDiscard", "the soil stays at t = %.9g s, the last successful time: "
                     "retry from there with a shorter step (or restore an FMU state)", time);
        }
        s->discards++;
        s->discarded_step = step;
        s->discarded_inputs = hash;
    }
    return status;
}

/* ---------------------------------------------------------------------------- FMU states */

/* Whether `snapshot` was taken by `s` (and not by another instance, which numbers its states alike). */
static int owned(const Soil *s, const SoilSnapshot *snapshot) {
    return snapshot->owner == (const void *)s && snapshot->serial == s->serial;
}

static SoilStatus state_request(Soil *s, uint32_t kind, unsigned id, const char *doing) {
    uint32_t payload = (uint32_t)id;
    return request(s, kind, &payload, sizeof payload, s->real[VR_STEP_TIMEOUT], "server_step_timeout", doing);
}

SoilStatus soil_get_state(Soil *s, SoilSnapshot **state) {
    SoilSnapshot *snapshot = *state;
    size_t size = (size_t)s->wheel_count * W_SIZE * sizeof(double);
    if (refused_after_error(s, "taking an FMU state")) return SOIL_ERROR;
    if (s->failed || !s->initialized) {
        soil_log(s, SOIL_ERROR, "logStatusError", "an FMU state can be taken after initialization, while the "
                 "soil server runs");
        return SOIL_ERROR;
    }
    if (snapshot && !owned(s, snapshot)) {
        soil_log(s, SOIL_ERROR, "logStatusError", "the FMU state belongs to another instance of the FMU: take "
                 "this instance's own (an FMU state is its instance's soil)");
        return SOIL_ERROR;
    }
    if (snapshot && snapshot->generation != s->generation) {
        soil_log(s, SOIL_ERROR, "logStatusError", "the FMU state belongs to a soil that was reset or stopped");
        return SOIL_ERROR;
    }
    if (!snapshot) {
        snapshot = calloc(1, sizeof(SoilSnapshot));
        if (!snapshot || !(snapshot->wheel = malloc(size))) {
            free(snapshot);
            return server_failed(s, "out of memory");
        }
        snapshot->id = ++s->next_state;
        snapshot->generation = s->generation;
        snapshot->owner = s;
        snapshot->serial = s->serial;
    }
    if (state_request(s, MSG_SAVE, snapshot->id, "saving an FMU state") != SOIL_OK) {
        if (!*state) {
            free(snapshot->wheel);
            free(snapshot);
        }
        return SOIL_ERROR;
    }
    memcpy(snapshot->real, s->real, sizeof s->real);
    memcpy(snapshot->wheel, s->wheel, size);
    snapshot->discards = s->discards;
    snapshot->terminated = s->terminated;
    snapshot->discarded_step = s->discarded_step;
    snapshot->discarded_inputs = s->discarded_inputs;
    *state = snapshot;
    return SOIL_OK;
}

SoilStatus soil_set_state(Soil *s, const SoilSnapshot *snapshot) {
    if (!snapshot || !owned(s, snapshot) || s->failed || !s->initialized ||
        snapshot->generation != s->generation) {
        soil_log(s, SOIL_ERROR, "logStatusError", "the FMU state cannot be restored: %s",
                 !snapshot             ? "none given"
                 : !owned(s, snapshot) ? "it belongs to another instance of the FMU (an FMU state is its instance's soil)"
                                       : "it belongs to a soil that was reset or stopped, or the server failed");
        return SOIL_ERROR;
    }
    if (state_request(s, MSG_RESTORE, snapshot->id, "restoring an FMU state") != SOIL_OK) return SOIL_ERROR;
    memcpy(s->real, snapshot->real, sizeof s->real);
    memcpy(s->wheel, snapshot->wheel, (size_t)s->wheel_count * W_SIZE * sizeof(double));
    s->discards = snapshot->discards;
    s->terminated = snapshot->terminated;
    s->discarded_step = snapshot->discarded_step;
    s->discarded_inputs = snapshot->discarded_inputs;
    s->in_error = 0;
    return SOIL_OK;
}

SoilStatus soil_free_state(Soil *s, SoilSnapshot **state) {
    SoilStatus status = SOIL_OK;
    if (!*state) return SOIL_OK;
    if (!owned(s, *state)) { /* not ours to free: its own instance's server keeps its soil */
        soil_log(s, SOIL_ERROR, "logStatusError", "the FMU state belongs to another instance of the FMU: free it "
                 "with that instance");
        return SOIL_ERROR;
    }
    if (s->initialized && !s->failed && (*state)->generation == s->generation)
        status = state_request(s, MSG_FREE, (*state)->id, "freeing an FMU state");
    free((*state)->wheel);
    free(*state);
    *state = NULL;
    return status;
}

void soil_stop(Soil *s) {
    char how[128];
    if (s->pid > 0 && s->socket >= 0) {
        uint32_t answer, size;
        char *text = NULL;
        if (send_message(s, MSG_BYE, "", 0, STOP_WAIT, "stopping") == SOIL_OK &&
            receive_message(s, &answer, &text, &size, STOP_WAIT, NULL, "stopping") == SOIL_OK) {
            close_channel(s);
            if (!reap(s, STOP_WAIT, how, sizeof how))
                soil_log(s, SOIL_WARNING, "logStatusWarning", "the soil server did not stop within %g s; killed",
                         STOP_WAIT);
        }
        free(text);
    }
    kill_server(s); /* also when it did not stop: never leave a process behind */
    s->stopped = s->stopped || s->initialized;
    s->initialized = 0;
}

void soil_reset(Soil *s) {
    soil_stop(s);
    s->failed = s->in_error = s->stopped = 0;
    s->tail[0] = 0;
    restore_start_values(s);
}

void soil_free(Soil *s) {
    if (!s) return;
    soil_stop(s);
    free(s->instance_name);
    free(s->resources);
    free(s->python);
    free(s->device);
    free(s->default_python);
    free(s->wheel);
    free(s->wheel_start);
    free(s);
}

/* ---------------------------------------------------------------------------- variables */

static double *wheel_value(Soil *s, unsigned vr) {
    unsigned wheel = vr / VR_WHEEL, offset = vr % VR_WHEEL;
    if (wheel < 1 || wheel > (unsigned)s->wheel_count || offset >= W_SIZE) return NULL;
    return s->wheel + (wheel - 1) * W_SIZE + offset;
}

SoilStatus soil_get_real(Soil *s, unsigned vr, double *value) {
    double *w;
    if (vr < VR_REAL_PARAMETERS) {
        *value = s->real[vr];
        return SOIL_OK;
    }
    w = wheel_value(s, vr);
    if (!w || vr % VR_WHEEL == W_CONTACTS) {
        soil_log(s, SOIL_ERROR, "logStatusError", "no Float64/Real variable has value reference %u", vr);
        return SOIL_ERROR;
    }
    *value = *w;
    return SOIL_OK;
}

static const char *const PARAMETER_NAMES[VR_REAL_PARAMETERS] = {
    "time", "dem_step", "gravity.x", "gravity.y", "gravity.z", "server_start_timeout", "server_step_timeout"};
static const char *const INPUT_NAMES[W_INPUTS] = {
    "position.x", "position.y", "position.z", "orientation.w", "orientation.x", "orientation.y", "orientation.z",
    "velocity.x", "velocity.y", "velocity.z", "angular_velocity.x", "angular_velocity.y", "angular_velocity.z"};

/* A value is refused here, with the instance left as it was, rather than by the server, whose error
   ends the instance: the master can restore an FMU state and go on. */
SoilStatus soil_set_real(Soil *s, unsigned vr, double value) {
    double *w = vr >= VR_WHEEL ? wheel_value(s, vr) : NULL;
    if (refused_after_error(s, "setting a value")) return SOIL_ERROR;
    if (vr >= VR_DEM_STEP && vr < VR_REAL_PARAMETERS) {
        int positive = vr == VR_DEM_STEP || vr == VR_START_TIMEOUT || vr == VR_STEP_TIMEOUT;
        if (s->initialized) {
            soil_log(s, SOIL_ERROR, "logStatusError", "parameter %s is fixed: set it before initialization ends",
                     PARAMETER_NAMES[vr]);
            return SOIL_ERROR;
        }
        if (!isfinite(value) || (positive && !(value > 0))) {
            soil_log(s, SOIL_ERROR, "logStatusError", "parameter %s must be a finite number%s, got %.17g",
                     PARAMETER_NAMES[vr], positive ? " > 0 [s]" : " [m/s2]", value);
            return SOIL_ERROR;
        }
        s->real[vr] = value;
        return SOIL_OK;
    }
    if (!w || vr % VR_WHEEL >= W_INPUTS) {
        soil_log(s, SOIL_ERROR, "logStatusError", "value reference %u is not a settable Float64/Real variable "
                 "(wheel inputs and parameters are)", vr);
        return SOIL_ERROR;
    }
    if (!isfinite(value)) {
        soil_log(s, SOIL_ERROR, "logStatusError", "input wheel_%u.%s must be finite, got %g; it keeps %.17g",
                 vr / VR_WHEEL - 1, INPUT_NAMES[vr % VR_WHEEL], value, *w);
        return SOIL_ERROR;
    }
    *w = value;
    return SOIL_OK;
}

SoilStatus soil_get_integer(Soil *s, unsigned vr, int *value) {
    double *w = vr >= VR_WHEEL ? wheel_value(s, vr) : NULL;
    if (!w || vr % VR_WHEEL != W_CONTACTS) {
        soil_log(s, SOIL_ERROR, "logStatusError", "no Integer/Int32 variable has value reference %u", vr);
        return SOIL_ERROR;
    }
    *value = (int)*w;
    return SOIL_OK;
}

SoilStatus soil_get_string(Soil *s, unsigned vr, const char **value) {
    if (vr == VR_PYTHON) *value = s->python;
    else if (vr == VR_DEVICE) *value = s->device;
    else {
        soil_log(s, SOIL_ERROR, "logStatusError", "no String variable has value reference %u", vr);
        return SOIL_ERROR;
    }
    return SOIL_OK;
}

SoilStatus soil_set_string(Soil *s, unsigned vr, const char *value) {
    char **target = vr == VR_PYTHON ? &s->python : vr == VR_DEVICE ? &s->device : NULL;
    char *copy;
    if (refused_after_error(s, "setting a value")) return SOIL_ERROR;
    if (!target) {
        soil_log(s, SOIL_ERROR, "logStatusError", "no String variable has value reference %u", vr);
        return SOIL_ERROR;
    }
    if (s->initialized) {
        soil_log(s, SOIL_ERROR, "logStatusError", "parameter %s is fixed: set it before initialization ends",
                 vr == VR_PYTHON ? "python" : "device");
        return SOIL_ERROR;
    }
    copy = copy_text(value ? value : "");
    if (!copy) return SOIL_ERROR;
    free(*target);
    *target = copy;
    return SOIL_OK;
}
