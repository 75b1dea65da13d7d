/* mpcl_app: see mpcl_app.h. Compiled with Yaskawa's SDK against its motoPlus.h, or on a PC against
 * host/motoPlus.h and host/mp_host.c (sim_cell's controller, the tests and the fuzzer). */
#include "motoPlus.h"
#include "mpcl_app.h"

#include <stdio.h>
#include <string.h>

typedef struct {
    mpcl_session session;
    SEM_ID lock;                /* guards everything below that both tasks touch */
    int listen_fd, peer_fd;
    uint16_t port;
    uint32_t allowed_peer;      /* IPv4, host order; 0: any */
    uint32_t tick_us, period_cycles, cycles, periods, motion_errors;
    uint64_t clock_us;          /* the interpolation clock's own time: cycles x cycle */
    int32_t period_step[6];     /* this period's step and what is left of it to hand out */
    int32_t remaining[6];
    int configured, stop, have_lock;
    char config_error[MPCL_TEXT];
} mpcl_app;

static mpcl_app app = {0};

static const ULONG STATUS_SIGNALS[11] = {MPCL_IO_ALARM_MAJOR, MPCL_IO_ALARM_MINOR, MPCL_IO_ALARM_SYSTEM,
                                         MPCL_IO_ALARM_USER, MPCL_IO_ERROR, MPCL_IO_PLAY, MPCL_IO_REMOTE,
                                         MPCL_IO_SERVO_ON, MPCL_IO_ESTOP_EXTERNAL, MPCL_IO_ESTOP_PENDANT,
                                         MPCL_IO_ESTOP_CONTROLLER};

/* Servo on, play and remote mode, no alarm or error, no E-stop; a failed read is "not ready". */
static int controller_ready(void)
{
    MP_IO_INFO info[11];
    USHORT value[11];
    int i;
    for (i = 0; i < 11; ++i) info[i].ulAddr = STATUS_SIGNALS[i];
    if (mpReadIO(info, value, 11) != 0) return 0;
    return !value[0] && !value[1] && !value[2] && !value[3] && !value[4] && value[5] && value[6] && value[7] &&
           value[8] && value[9] && value[10];
}

static int read_pose(int32_t pose[6])
{
    MP_CTRL_GRP_SEND_DATA group;
    MP_CART_POS_RSP_DATA cart;
    int i;
    memset(&group, 0, sizeof group);
    group.sCtrlGrp = 0;  /* R1 */
    if (mpGetCartPos(&group, &cart) != 0) return -1;
    for (i = 0; i < 6; ++i) pose[i] = (int32_t)cart.lPos[i];
    return 0;
}

int mpcl_app_configure(void)
{
    MP_VAR_INFO info[MPCL_CONFIG_COUNT];
    LONG value[MPCL_CONFIG_COUNT];
    mpcl_limits limits;
    int i;
    memset(&limits, 0, sizeof limits);
    if (!app.have_lock) {
        app.lock = mpSemBCreate(SEM_Q_FIFO, SEM_FULL);
        app.have_lock = 1;
    }
    for (i = 0; i < MPCL_CONFIG_COUNT; ++i) {
        info[i].usType = MP_RESTYPE_VAR_D;
        info[i].usIndex = (USHORT)(MPCL_CONFIG_D_BASE + i);
    }
    app.configured = 0;
    app.listen_fd = app.peer_fd = -1;
    if (mpGetVarData(info, value, MPCL_CONFIG_COUNT) != 0) {
        snprintf(app.config_error, sizeof app.config_error, "cannot read D%03d..D%03d", MPCL_CONFIG_D_BASE,
                 MPCL_CONFIG_D_BASE + MPCL_CONFIG_COUNT - 1);
    } else {
        for (i = 0; i < 6; ++i) {
            limits.max_step[i] = (int32_t)value[i];
            limits.max_offset[i] = (int32_t)value[6 + i];
            limits.max_speed[i] = (int32_t)value[12 + i];
        }
        limits.max_watchdog_ms = value[18] > 0 ? (uint32_t)value[18] : 0u;
        app.tick_us = value[21] == 0 ? MPCL_DEFAULT_TICK_US : (value[21] > 0 ? (uint32_t)value[21] : 0u);
        app.period_cycles = value[19] > 0 && value[19] <= 250 ? (uint32_t)value[19] : 0u;
        limits.period_us = app.period_cycles * app.tick_us;
        app.port = value[20] == 0 ? (uint16_t)MPCL_DEFAULT_PORT : (uint16_t)value[20];
        app.allowed_peer = (uint32_t)value[22];
        if (value[20] < 0 || value[20] > 65535 || app.tick_us < 500u || app.tick_us > 100000u ||
            app.period_cycles == 0u) {
            snprintf(app.config_error, sizeof app.config_error,
                     "port %ld, period %ld cycles, cycle %ld us: port 0..65535, 1..250 cycles, 500..100000 us",
                     (long)value[20], (long)value[19], (long)value[21]);
        } else if (mpcl_limits_check(&limits, app.config_error, sizeof app.config_error) == 0) {
            app.configured = 1;
        }
    }
    if (!app.configured) {
        mpSetAlarm(MPCL_ALARM_CODE, app.config_error, 0);
        return -1;
    }
    mpcl_session_init(&app.session, &limits);
    app.session.ready = controller_ready();
    app.config_error[0] = '\0';
    app.cycles = app.periods = app.motion_errors = 0;
    app.clock_us = 0;
    memset(app.period_step, 0, sizeof app.period_step);
    memset(app.remaining, 0, sizeof app.remaining);
    return 0;
}

/* Sends what the session has to say (lock held). Sent under the lock so that a STATE and a FAULT leave
 * in the order the session wrote them; frames are a few dozen bytes, so mpSend does not wait. */
static void flush(void)
{
    mpcl_session *s = &app.session;
    if (s->out_len == 0u) return;
    if (app.peer_fd >= 0 && mpSend(app.peer_fd, (const char *)s->out, (int)s->out_len, 0) != (int)s->out_len) {
        mpcl_session_lost(s, "the bridge disconnected (a send failed)");  /* no FAULT: nobody to tell */
    }
    s->out_len = 0;
}

/* Forgets what is left of the period's step (the session ended, or a motion call failed), so that the
 * offset the session reports, and the period's step, count only what mpExRcsIncrementMove was given. */
static void drop_remaining(void)
{
    int i;
    for (i = 0; i < 6; ++i) {
        app.session.offset[i] -= app.remaining[i];
        app.period_step[i] -= app.remaining[i];
        app.remaining[i] = 0;
    }
}

void mpcl_app_accepted(int fd)
{
    mpSemTake(app.lock, WAIT_FOREVER);
    app.peer_fd = fd;
    mpcl_session_open(&app.session, mpGetRtc());
    mpSemGive(app.lock);
}

int mpcl_app_received(const uint8_t *data, size_t length)
{
    int close;
    mpSemTake(app.lock, WAIT_FOREVER);
    close = mpcl_session_feed(&app.session, data, length, mpGetRtc());
    flush();
    close = close || app.session.close;
    mpSemGive(app.lock);
    return close;
}

int mpcl_app_poll(void)
{
    int close;
    mpSemTake(app.lock, WAIT_FOREVER);
    close = mpcl_session_poll(&app.session, mpGetRtc());
    flush();
    mpSemGive(app.lock);
    return close;
}

void mpcl_app_gone(const char *why)
{
    mpSemTake(app.lock, WAIT_FOREVER);
    mpcl_session_closed(&app.session, why);
    app.peer_fd = -1;
    drop_remaining();  /* no session: nothing more is handed out */
    mpSemGive(app.lock);
}

/* This cycle's share of what is left of the period's step: the step spread evenly over the period's
 * cycles, so the arm never moves faster than the configured speed within a period. */
static void share(int32_t out[6], uint32_t cycles_left)
{
    int i;
    for (i = 0; i < 6; ++i) {
        int32_t part = (int32_t)(app.remaining[i] / (int32_t)cycles_left);
        int32_t rest = (int32_t)(app.remaining[i] % (int32_t)cycles_left);
        if (rest != 0) part += rest > 0 ? 1 : -1;
        out[i] = part;
        app.remaining[i] -= part;
    }
}

static int move(const int32_t increment[6])
{
    MP_EXPOS_DATA data;
    static const UCHAR types[4] = {MP_INC_BF_DTYPE, MP_INC_RF_DTYPE, MP_INC_TF_DTYPE, MP_INC_UF_DTYPE};
    int i, ret;
    memset(&data, 0, sizeof data);
    data.ctrl_grp = 1u;  /* R1 */
    data.grp_pos_info[0].pos_tag.data[0] = 0x3F;  /* six axes */
    data.grp_pos_info[0].pos_tag.data[2] = app.session.tool;
    data.grp_pos_info[0].pos_tag.data[3] = types[app.session.frame & 3u];
    data.grp_pos_info[0].pos_tag.data[4] = app.session.user_frame;
    for (i = 0; i < 6; ++i) data.grp_pos_info[0].pos[i] = (LONG)increment[i];
    ret = mpExRcsIncrementMove(&data);
    if (ret != 0) {
        char why[MPCL_TEXT];
        app.motion_errors++;
        snprintf(why, sizeof why, "mpExRcsIncrementMove returned %d", ret);
        mpcl_session_alarm(&app.session, why);  /* latched: no more motion until a new HELLO */
    }
    return ret;
}

void mpcl_app_cycle(void)
{
    int32_t increment[6];
    uint32_t phase;
    int i, any = 0;
    mpSemTake(app.lock, WAIT_FOREVER);
    app.cycles++;
    app.clock_us += app.tick_us;
    phase = app.cycles % app.period_cycles;
    if (phase == 0u) {
        int32_t pose[6];
        int ready = controller_ready();
        if (read_pose(pose) != 0) {
            memcpy(pose, app.session.pose, sizeof pose);
            ready = 0;  /* a controller that cannot say where the arm is must not move it */
        }
        if (app.session.armed) app.periods++;
        mpcl_session_period(&app.session, mpGetRtc(), app.clock_us, pose, ready, app.period_step);
        memcpy(app.remaining, app.period_step, sizeof app.remaining);
        flush();  /* a failed STATE ends the session before any of the step is handed out */
    }
    if (app.session.armed && !app.session.close) {  /* a session whose link failed moves no more */
        share(increment, app.period_cycles - (phase == 0u ? 0u : phase));
        for (i = 0; i < 6; ++i) any |= increment[i] != 0;
        if (any && move(increment) != 0) {
            for (i = 0; i < 6; ++i) app.remaining[i] += increment[i];  /* not applied either */
        }
    }
    if (!app.session.armed || app.session.close) drop_remaining();
    mpSemGive(app.lock);
}

void mpcl_app_read_status(mpcl_app_status *out)
{
    mpSemTake(app.lock, WAIT_FOREVER);
    out->stats = app.session.stats;
    memcpy(out->offset, app.session.offset, sizeof out->offset);
    memcpy(out->period_step, app.period_step, sizeof out->period_step);
    memcpy(out->session_step, app.session.step, sizeof out->session_step);
    memcpy(out->session_offset, app.session.offset_bound, sizeof out->session_offset);
    out->session_watchdog_ms = app.session.watchdog_ms;
    out->periods = app.periods;
    out->cycles = app.cycles;
    out->motion_errors = app.motion_errors;
    out->armed = app.session.armed;
    out->connected = app.session.connected;
    out->configured = app.configured;
    out->pending = app.session.pending;
    out->closing = app.session.close;
    memcpy(out->config_error, app.config_error, sizeof out->config_error);
    mpSemGive(app.lock);
}

/* ---------------------------------------------------------------- the tasks */

static void drop_peer(const char *why)
{
    int fd = app.peer_fd;
    mpcl_app_gone(why);
    if (fd >= 0) mpClose(fd);
}

/* The controller drops the connection, after reading what the peer had already sent: a STOP that came
 * just before the link failed ends the session as the STOP it was. */
static void read_then_drop(int peer, uint8_t *buffer, int capacity)
{
    int round;
    for (round = 0; round < 8; ++round) {
        fd_set readable;
        struct timeval now = {0, 0};
        int n;
        FD_ZERO(&readable);
        FD_SET(peer, &readable);
        if (mpSelect(peer + 1, &readable, NULL, NULL, &now) <= 0) break;
        n = mpRecv(peer, (char *)buffer, capacity, 0);
        if (n <= 0) break;
        mpcl_app_received(buffer, (size_t)n);
    }
    drop_peer("dropped by the controller");
}

void mpcl_server_task(int a1, int a2, int a3, int a4, int a5, int a6, int a7, int a8, int a9, int a10)
{
    struct sockaddr_in address;
    uint8_t buffer[2048];
    int one = 1;
    (void)a1; (void)a2; (void)a3; (void)a4; (void)a5; (void)a6; (void)a7; (void)a8; (void)a9; (void)a10;
    app.listen_fd = mpSocket(AF_INET, SOCK_STREAM, 0);
    memset(&address, 0, sizeof address);
    address.sin_family = AF_INET;
    address.sin_port = mpHtons(app.port);
    address.sin_addr.s_addr = mpHtonl(INADDR_ANY);
    if (app.listen_fd < 0 || mpBind(app.listen_fd, (struct sockaddr *)&address, sizeof address) < 0 ||
        mpListen(app.listen_fd, 1) < 0) {
        mpSetAlarm(MPCL_ALARM_CODE, "mpcl: cannot listen on its TCP port", 1);
        return;
    }
    while (!app.stop) {
        fd_set readable;
        struct timeval timeout;
        int width = app.listen_fd, peer = app.peer_fd;
        FD_ZERO(&readable);
        FD_SET(app.listen_fd, &readable);
        if (peer >= 0) {
            FD_SET(peer, &readable);
            if (peer > width) width = peer;
        }
        timeout.tv_sec = 0;
        timeout.tv_usec = 20000;  /* the HELLO deadline and a close the clock task asked for, within 20 ms */
        if (mpSelect(width + 1, &readable, NULL, NULL, &timeout) < 0) continue;
        if (FD_ISSET(app.listen_fd, &readable)) {
            struct sockaddr_in from;
            int length = (int)sizeof from;
            int fd = mpAccept(app.listen_fd, (struct sockaddr *)&from, &length);
            int stranger = fd >= 0 && app.allowed_peer != 0u && mpNtohl(from.sin_addr.s_addr) != app.allowed_peer;
            if (fd >= 0 && (peer >= 0 || stranger)) {  /* one bridge, from its address: others closed at once */
                mpClose(fd);
                mpSemTake(app.lock, WAIT_FOREVER);
                app.session.stats.refused_peers++;
                mpSemGive(app.lock);
            } else if (fd >= 0) {
                mpSetsockopt(fd, IPPROTO_TCP, TCP_NODELAY, (char *)&one, sizeof one);
                mpcl_app_accepted(fd);
                peer = fd;
            }
        }
        if (peer >= 0 && FD_ISSET(peer, &readable)) {
            int n = mpRecv(peer, (char *)buffer, (int)sizeof buffer, 0);
            if (n <= 0) {
                drop_peer(n == 0 ? "the bridge disconnected" : "the bridge disconnected (a receive failed)");
                continue;
            }
            if (mpcl_app_received(buffer, (size_t)n)) {
                read_then_drop(peer, buffer, (int)sizeof buffer);
                continue;
            }
        }
        if (peer >= 0 && mpcl_app_poll()) read_then_drop(peer, buffer, (int)sizeof buffer);
    }
    if (app.peer_fd >= 0) drop_peer("the application stopped");
    mpClose(app.listen_fd);
}

void mpcl_clock_task(int a1, int a2, int a3, int a4, int a5, int a6, int a7, int a8, int a9, int a10)
{
    (void)a1; (void)a2; (void)a3; (void)a4; (void)a5; (void)a6; (void)a7; (void)a8; (void)a9; (void)a10;
    while (mpClkAnnounce(MP_INTERPOLATION_CLK) >= 0) mpcl_app_cycle();
    app.stop = 1;  /* no clock, no motion: the socket task lets the bridge go and ends */
}

void mpUsrRoot(int arg1, int arg2, int arg3, int arg4, int arg5, int arg6, int arg7, int arg8, int arg9, int arg10)
{
    (void)arg1; (void)arg2; (void)arg3; (void)arg4; (void)arg5; (void)arg6; (void)arg7; (void)arg8; (void)arg9;
    (void)arg10;
    app.stop = 0;
    if (mpcl_app_configure() == 0) {
        mpCreateTask(MP_PRI_IP_CLK_TAKE, MP_STACK_SIZE, mpcl_clock_task, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
        mpCreateTask(MP_PRI_TIME_NORMAL, MP_STACK_SIZE, mpcl_server_task, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
    }
    mpExitUsrRoot;
}
