/* mp_host: host/motoPlus.h implemented on POSIX threads and sockets, with the hooks of mph.h. Only the
 * application's view matters here: a clock that ticks when the simulation says, motion calls that report
 * to the simulation, and the controller's variables and signals as the simulation set them. */
#include "motoPlus.h"
#include "mph.h"

#include <arpa/inet.h>
#include <errno.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

/* the application's entry point, as the controller calls it at start-up */
void mpUsrRoot(int arg1, int arg2, int arg3, int arg4, int arg5, int arg6, int arg7, int arg8, int arg9, int arg10);

enum { MAX_TASKS = 8, MAX_SEMS = 16, MAX_IO = 64, MAX_D = 1000, DELAY_SLOTS = 256, DELAY_BYTES = 512 };

typedef struct { FUNCPTR entry; int args[10]; } task_start;
typedef struct { pthread_mutex_t mutex; pthread_cond_t cond; int full; } host_sem;
typedef struct { uint64_t due_ns; int fd; int length; char data[DELAY_BYTES]; } delayed_frame;

static struct {
    pthread_mutex_t mutex;      /* everything below but the clock and the delay queue */
    int32_t var_d[MAX_D];
    uint32_t io_address[MAX_IO];
    int io_value[MAX_IO], io_count;
    char bind_address[64];
    int bind_port;              /* -1: the application's own; else this (0: any free port) */
    char bound_address[64];  /* where the application really listens */
    int port;
    int32_t pose[6];
    int motion_error;
    int32_t increment[6];
    char alarm[256];
    int virtual_clock;          /* the fuzzer's: mpGetRtc reads virtual_ms */
    uint32_t virtual_ms;
    double state_drop;
    uint32_t delay_us, fail_after_states, states_sent;
    uint64_t rng;
    pthread_t tasks[MAX_TASKS];
    task_start starts[MAX_TASKS];
    int task_count;
    host_sem sems[MAX_SEMS];
    int sem_count;
} host = {.mutex = PTHREAD_MUTEX_INITIALIZER};

static struct {
    pthread_mutex_t mutex;
    pthread_cond_t tick_cv, done_cv;
    uint64_t issued, released, completed;
    uint32_t overruns;
    int stopping, ready;
} clk = {.mutex = PTHREAD_MUTEX_INITIALIZER};

static struct {
    pthread_mutex_t mutex;
    pthread_cond_t cv;
    delayed_frame slots[DELAY_SLOTS];
    int head, count, running, stopping;
    pthread_t thread;
} later = {.mutex = PTHREAD_MUTEX_INITIALIZER};

static uint64_t now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (uint64_t)t.tv_sec * 1000000000u + (uint64_t)t.tv_nsec;
}

static struct timespec deadline_in(uint64_t ns)
{
    uint64_t due = now_ns() + ns;
    struct timespec t;
    t.tv_sec = (time_t)(due / 1000000000u);
    t.tv_nsec = (long)(due % 1000000000u);
    return t;
}

static void init_clock(void)
{
    pthread_condattr_t attr;
    if (clk.ready) return;
    pthread_condattr_init(&attr);
    pthread_condattr_setclock(&attr, CLOCK_MONOTONIC);
    pthread_cond_init(&clk.tick_cv, &attr);
    pthread_cond_init(&clk.done_cv, &attr);
    pthread_cond_init(&later.cv, &attr);
    pthread_condattr_destroy(&attr);
    clk.ready = 1;
}

/* ---------------------------------------------------------------- the simulation's hooks */

void mph_reset(void)
{
    pthread_mutex_lock(&host.mutex);
    memset(host.var_d, 0, sizeof host.var_d);
    host.io_count = 0;
    strcpy(host.bind_address, "127.0.0.1");
    host.bind_port = -1;
    host.bound_address[0] = '\0';
    host.port = -1;
    memset(host.pose, 0, sizeof host.pose);
    memset(host.increment, 0, sizeof host.increment);
    host.motion_error = 0;
    host.alarm[0] = '\0';
    host.state_drop = 0.0;
    host.delay_us = host.fail_after_states = host.states_sent = 0;
    host.rng = 0x9E3779B97F4A7C15u;
    pthread_mutex_unlock(&host.mutex);
    /* ready to move: servo on, play and remote mode, no E-stop pressed */
    mph_set_io(50054, 1);
    mph_set_io(80011, 1);
    mph_set_io(50073, 1);
    mph_set_io(80025, 1);
    mph_set_io(80026, 1);
    mph_set_io(80027, 1);
    pthread_mutex_lock(&clk.mutex);
    init_clock();
    clk.issued = clk.released = clk.completed = 0;
    clk.overruns = 0;
    clk.stopping = 0;
    pthread_mutex_unlock(&clk.mutex);
}

void mph_set_var_d(int index, int32_t value)
{
    if (index < 0 || index >= MAX_D) return;
    pthread_mutex_lock(&host.mutex);
    host.var_d[index] = value;
    pthread_mutex_unlock(&host.mutex);
}

void mph_set_io(uint32_t address, int value)
{
    int i;
    pthread_mutex_lock(&host.mutex);
    for (i = 0; i < host.io_count && host.io_address[i] != address; ++i) {}
    if (i < MAX_IO) {
        host.io_address[i] = address;
        host.io_value[i] = value;
        if (i == host.io_count) host.io_count++;
    }
    pthread_mutex_unlock(&host.mutex);
}

void mph_set_bind_address(const char *ipv4)
{
    pthread_mutex_lock(&host.mutex);
    snprintf(host.bind_address, sizeof host.bind_address, "%s", ipv4);
    pthread_mutex_unlock(&host.mutex);
}

void mph_set_bind_port(int port)
{
    pthread_mutex_lock(&host.mutex);
    host.bind_port = port;
    pthread_mutex_unlock(&host.mutex);
}

void mph_set_cart_pos(const int32_t pose[6])
{
    pthread_mutex_lock(&host.mutex);
    memcpy(host.pose, pose, sizeof host.pose);
    pthread_mutex_unlock(&host.mutex);
}

void mph_set_motion_error(int code)
{
    pthread_mutex_lock(&host.mutex);
    host.motion_error = code;
    pthread_mutex_unlock(&host.mutex);
}

void mph_set_net_faults(double state_drop, uint32_t delay_us, uint32_t fail_after_states, uint64_t seed)
{
    pthread_mutex_lock(&host.mutex);
    host.state_drop = state_drop;
    host.delay_us = delay_us;
    host.fail_after_states = fail_after_states;
    host.states_sent = 0;
    host.rng = seed ? seed : 1u;
    pthread_mutex_unlock(&host.mutex);
}

int mph_start(void)
{
    int tasks;
    mpUsrRoot(0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
    pthread_mutex_lock(&host.mutex);
    tasks = host.task_count;
    pthread_mutex_unlock(&host.mutex);
    return tasks == 2 ? 0 : -1;
}

int mph_port(void)
{
    int i, port = -1;
    for (i = 0; i < 400 && port < 0; ++i) {  /* the socket task binds as it starts: up to 2 s */
        pthread_mutex_lock(&host.mutex);
        port = host.port;
        pthread_mutex_unlock(&host.mutex);
        if (port < 0) usleep(5000);
    }
    return port;
}

int mph_tick(uint32_t timeout_us)
{
    struct timespec deadline = deadline_in((uint64_t)timeout_us * 1000u);
    int late = 0;
    uint64_t tick;
    pthread_mutex_lock(&clk.mutex);
    tick = ++clk.issued;
    pthread_cond_broadcast(&clk.tick_cv);
    while (clk.completed < tick && !clk.stopping) {
        if (pthread_cond_timedwait(&clk.done_cv, &clk.mutex, &deadline) == ETIMEDOUT) {
            late = 1;
            clk.overruns++;
            break;
        }
    }
    pthread_mutex_unlock(&clk.mutex);
    return late;
}

void mph_take_increment(int32_t out[6])
{
    pthread_mutex_lock(&host.mutex);
    memcpy(out, host.increment, sizeof host.increment);
    memset(host.increment, 0, sizeof host.increment);
    pthread_mutex_unlock(&host.mutex);
}

uint32_t mph_overruns(void)
{
    uint32_t n;
    pthread_mutex_lock(&clk.mutex);
    n = clk.overruns;
    pthread_mutex_unlock(&clk.mutex);
    return n;
}

const char *mph_bound_address(void)
{
    return host.bound_address;
}

const char *mph_last_alarm(void)
{
    return host.alarm;
}

void mph_stop(void)
{
    int i, count;
    pthread_mutex_lock(&clk.mutex);
    clk.stopping = 1;
    pthread_cond_broadcast(&clk.tick_cv);
    pthread_cond_broadcast(&clk.done_cv);
    pthread_mutex_unlock(&clk.mutex);
    pthread_mutex_lock(&host.mutex);
    count = host.task_count;
    pthread_mutex_unlock(&host.mutex);
    for (i = 0; i < count; ++i) pthread_join(host.tasks[i], NULL);
    pthread_mutex_lock(&host.mutex);
    host.task_count = 0;
    pthread_mutex_unlock(&host.mutex);
    pthread_mutex_lock(&later.mutex);
    later.stopping = 1;
    pthread_cond_broadcast(&later.cv);
    pthread_mutex_unlock(&later.mutex);
    if (later.running) pthread_join(later.thread, NULL);
    later.running = later.stopping = 0;
    later.count = 0;
}

/* ---------------------------------------------------------------- tasks, clock, semaphores */

static void *run_task(void *arg)
{
    task_start *t = (task_start *)arg;
    t->entry(t->args[0], t->args[1], t->args[2], t->args[3], t->args[4], t->args[5], t->args[6], t->args[7],
             t->args[8], t->args[9]);
    return NULL;
}

int mpCreateTask(int priority, int stackSize, FUNCPTR entryPt, int arg1, int arg2, int arg3, int arg4, int arg5,
                 int arg6, int arg7, int arg8, int arg9, int arg10)
{
    int id;
    task_start *t;
    (void)priority;
    (void)stackSize;
    pthread_mutex_lock(&host.mutex);
    id = host.task_count;
    if (id >= MAX_TASKS) {
        pthread_mutex_unlock(&host.mutex);
        return ERROR;
    }
    t = &host.starts[id];
    t->entry = entryPt;
    t->args[0] = arg1; t->args[1] = arg2; t->args[2] = arg3; t->args[3] = arg4; t->args[4] = arg5;
    t->args[5] = arg6; t->args[6] = arg7; t->args[7] = arg8; t->args[8] = arg9; t->args[9] = arg10;
    if (pthread_create(&host.tasks[id], NULL, run_task, t) != 0) {
        pthread_mutex_unlock(&host.mutex);
        return ERROR;
    }
    host.task_count++;
    pthread_mutex_unlock(&host.mutex);
    return id + 1;
}

STATUS mpClkAnnounce(int clk_id)
{
    if (clk_id != MP_INTERPOLATION_CLK) return ERROR;
    pthread_mutex_lock(&clk.mutex);
    init_clock();
    clk.completed = clk.released;  /* the last cycle's work is done */
    pthread_cond_broadcast(&clk.done_cv);
    while (clk.issued == clk.released && !clk.stopping) pthread_cond_wait(&clk.tick_cv, &clk.mutex);
    if (clk.stopping) {
        pthread_mutex_unlock(&clk.mutex);
        return ERROR;
    }
    clk.overruns += (uint32_t)(clk.issued - clk.released - 1u);  /* ticks that came while this task was late */
    clk.released = clk.issued;
    pthread_mutex_unlock(&clk.mutex);
    return OK;
}

ULONG mpGetRtc(void)
{
    if (host.virtual_clock) return host.virtual_ms;
    return (ULONG)(now_ns() / 1000000u);
}

void mph_virtual_clock(uint32_t start_ms)
{
    host.virtual_clock = 1;
    host.virtual_ms = start_ms;
}

void mph_advance_ms(uint32_t ms)
{
    host.virtual_ms += ms;
}

SEM_ID mpSemBCreate(int options, int initialState)
{
    int id;
    (void)options;
    pthread_mutex_lock(&host.mutex);
    id = host.sem_count < MAX_SEMS ? host.sem_count++ : -1;
    if (id >= 0) {
        pthread_mutex_init(&host.sems[id].mutex, NULL);
        pthread_cond_init(&host.sems[id].cond, NULL);
        host.sems[id].full = initialState == SEM_FULL;
    }
    pthread_mutex_unlock(&host.mutex);
    return id < 0 ? 0 : id + 1;
}

STATUS mpSemTake(SEM_ID semId, int timeout)
{
    host_sem *s;
    if (semId < 1 || semId > host.sem_count) return ERROR;
    s = &host.sems[semId - 1];
    pthread_mutex_lock(&s->mutex);
    while (!s->full) {
        if (timeout == NO_WAIT) {
            pthread_mutex_unlock(&s->mutex);
            return ERROR;
        }
        pthread_cond_wait(&s->cond, &s->mutex);
    }
    s->full = 0;
    pthread_mutex_unlock(&s->mutex);
    return OK;
}

STATUS mpSemGive(SEM_ID semId)
{
    host_sem *s;
    if (semId < 1 || semId > host.sem_count) return ERROR;
    s = &host.sems[semId - 1];
    pthread_mutex_lock(&s->mutex);
    s->full = 1;
    pthread_cond_signal(&s->cond);
    pthread_mutex_unlock(&s->mutex);
    return OK;
}

/* ---------------------------------------------------------------- sockets */

int mpSocket(int domain, int type, int protocol)
{
    return socket(domain, type, protocol);
}

int mpBind(int s, struct sockaddr *name, int namelen)
{
    struct sockaddr_in address;
    socklen_t length = sizeof address;
    int one = 1;
    if (namelen != (int)sizeof address) return ERROR;
    memcpy(&address, name, sizeof address);
    pthread_mutex_lock(&host.mutex);
    inet_pton(AF_INET, host.bind_address, &address.sin_addr);  /* the host build: loopback, not every interface */
    if (host.bind_port >= 0) address.sin_port = htons((uint16_t)host.bind_port);  /* the simulation's port */
    pthread_mutex_unlock(&host.mutex);
    setsockopt(s, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    if (bind(s, (struct sockaddr *)&address, sizeof address) != 0) return ERROR;
    if (getsockname(s, (struct sockaddr *)&address, &length) == 0) {
        pthread_mutex_lock(&host.mutex);
        inet_ntop(AF_INET, &address.sin_addr, host.bound_address, sizeof host.bound_address);
        host.port = ntohs(address.sin_port);
        pthread_mutex_unlock(&host.mutex);
    }
    return OK;
}

int mpListen(int s, int backlog)
{
    return listen(s, backlog);
}

int mpAccept(int s, struct sockaddr *addr, int *addrlen)
{
    socklen_t length = addrlen ? (socklen_t)*addrlen : 0;
    int fd = accept(s, addr, addr ? &length : NULL);
    if (addrlen) *addrlen = (int)length;
    return fd;
}

int mpRecv(int s, char *buf, int bufLen, int flags)
{
    return (int)recv(s, buf, (size_t)bufLen, flags);
}

static void *send_later(void *arg)
{
    (void)arg;
    pthread_mutex_lock(&later.mutex);
    while (!later.stopping) {
        delayed_frame *f;
        if (later.count == 0) {
            pthread_cond_wait(&later.cv, &later.mutex);
            continue;
        }
        f = &later.slots[later.head];
        if (now_ns() < f->due_ns) {
            struct timespec due;
            due.tv_sec = (time_t)(f->due_ns / 1000000000u);
            due.tv_nsec = (long)(f->due_ns % 1000000000u);
            pthread_cond_timedwait(&later.cv, &later.mutex, &due);
            continue;
        }
        send(f->fd, f->data, (size_t)f->length, MSG_NOSIGNAL);
        later.head = (later.head + 1) % DELAY_SLOTS;
        later.count--;
    }
    pthread_mutex_unlock(&later.mutex);
    return NULL;
}

static int is_state(const char *buf, int length)
{
    return length > 9 && (uint8_t)buf[9] == 3u;  /* length prefix, magic, version, then the type */
}

int mpSend(int s, const char *buf, int bufLen, int flags)
{
    uint32_t delay_us;
    int drop = 0, fail = 0;
    pthread_mutex_lock(&host.mutex);
    delay_us = host.delay_us;
    if (is_state(buf, bufLen)) {
        host.rng ^= host.rng << 13;
        host.rng ^= host.rng >> 7;
        host.rng ^= host.rng << 17;
        drop = host.state_drop > 0.0 && (double)(host.rng >> 11) / 9007199254740992.0 < host.state_drop;
        if (!drop && host.fail_after_states && ++host.states_sent >= host.fail_after_states) {
            host.fail_after_states = 0;
            fail = 1;
        }
    }
    pthread_mutex_unlock(&host.mutex);
    if (fail) {
        shutdown(s, SHUT_RDWR);  /* the link breaks, as a pulled cable or a crashed switch does */
        return ERROR;
    }
    if (drop) return bufLen;
    if (delay_us > 0u && bufLen <= DELAY_BYTES) {
        pthread_mutex_lock(&later.mutex);
        if (!later.running) {
            later.stopping = 0;
            later.running = pthread_create(&later.thread, NULL, send_later, NULL) == 0;
        }
        if (later.count < DELAY_SLOTS) {
            delayed_frame *f = &later.slots[(later.head + later.count) % DELAY_SLOTS];
            f->due_ns = now_ns() + (uint64_t)delay_us * 1000u;
            f->fd = s;
            f->length = bufLen;
            memcpy(f->data, buf, (size_t)bufLen);
            later.count++;
            pthread_cond_signal(&later.cv);
        }
        pthread_mutex_unlock(&later.mutex);
        return bufLen;
    }
    return (int)send(s, buf, (size_t)bufLen, flags | MSG_NOSIGNAL);
}

int mpSelect(int width, fd_set *readFds, fd_set *writeFds, fd_set *exceptFds, struct timeval *timeout)
{
    return select(width, readFds, writeFds, exceptFds, timeout);
}

int mpSetsockopt(int s, int level, int optname, char *optval, int optlen)
{
    return setsockopt(s, level, optname, optval, (socklen_t)optlen);
}

STATUS mpClose(int fd)
{
    return close(fd) == 0 ? OK : ERROR;
}

USHORT mpHtons(USHORT hostshort)
{
    return htons(hostshort);
}

ULONG mpHtonl(ULONG hostlong)
{
    return htonl(hostlong);
}

ULONG mpNtohl(ULONG netlong)
{
    return ntohl(netlong);
}

/* ---------------------------------------------------------------- variables, I/O, alarms, motion */

LONG mpGetVarData(MP_VAR_INFO *sData, LONG *rData, LONG num)
{
    LONG i;
    pthread_mutex_lock(&host.mutex);
    for (i = 0; i < num; ++i) {
        if (sData[i].usType != MP_RESTYPE_VAR_D || sData[i].usIndex >= MAX_D) {
            pthread_mutex_unlock(&host.mutex);
            return ERROR;
        }
        rData[i] = host.var_d[sData[i].usIndex];
    }
    pthread_mutex_unlock(&host.mutex);
    return OK;
}

LONG mpReadIO(MP_IO_INFO *sData, USHORT *rData, LONG num)
{
    LONG i;
    int k;
    pthread_mutex_lock(&host.mutex);
    for (i = 0; i < num; ++i) {
        rData[i] = 0;
        for (k = 0; k < host.io_count; ++k) {
            if (host.io_address[k] == sData[i].ulAddr) rData[i] = (USHORT)(host.io_value[k] != 0);
        }
    }
    pthread_mutex_unlock(&host.mutex);
    return OK;
}

int mpSetAlarm(SHORT alm_code, char *alm_msg, UCHAR sub_code)
{
    pthread_mutex_lock(&host.mutex);
    snprintf(host.alarm, sizeof host.alarm, "alarm %d.%u: %s", alm_code, sub_code, alm_msg);
    pthread_mutex_unlock(&host.mutex);
    return OK;
}

LONG mpGetCartPos(MP_CTRL_GRP_SEND_DATA *sData, MP_CART_POS_RSP_DATA *rData)
{
    int i;
    if (sData->sCtrlGrp != 0) return ERROR;
    memset(rData, 0, sizeof *rData);
    pthread_mutex_lock(&host.mutex);
    for (i = 0; i < 6; ++i) rData->lPos[i] = host.pose[i];
    pthread_mutex_unlock(&host.mutex);
    return OK;
}

int mpExRcsIncrementMove(MP_EXPOS_DATA *src_p)
{
    int i, error;
    if (src_p->ctrl_grp != 1u) return -3;  /* only R1 is simulated */
    pthread_mutex_lock(&host.mutex);
    error = host.motion_error;
    if (!error) {
        for (i = 0; i < 6; ++i) host.increment[i] += (int32_t)src_p->grp_pos_info[0].pos[i];
    }
    pthread_mutex_unlock(&host.mutex);
    return error;
}
