/*
 * mpcl_app: the MotoPlus application that serves motoplus_bridge (docs/motoplus_protocol.md).
 *
 * Two tasks: a socket task (one peer, the HELLO deadline) and a task on the interpolation clock that,
 * once per control period, reads the arm's pose and the controller's readiness, takes the session's step
 * and sends STATE, and every interpolation cycle hands mpExRcsIncrementMove its share of that step. One
 * semaphore guards the session, so the two tasks never disagree about whether it is armed.
 *
 * Configuration lives on the controller, in D variables the integrator sets from the pendant (never on
 * the network), read once at start-up; see firmware/motoplus/README.md:
 *   D[base+0..5]   max_step per control period (x y z um, rx ry rz 0.0001 deg)
 *   D[base+6..11]  max_offset from where the application started
 *   D[base+12..17] max_speed per second
 *   D[base+18]     longest watchdog a HELLO may ask for (ms)
 *   D[base+19]     control period in interpolation cycles (3: 12 ms on a 4 ms clock)
 *   D[base+20]     TCP port (0: MPCL_DEFAULT_PORT)
 *   D[base+21]     interpolation cycle in us (0: 4000, the YRC1000's)
 *   D[base+22]     the one bridge address accepted, IPv4 as a number (192.168.1.10: 0xC0A8010A); 0: any
 * A configuration outside mpcl_limits_check's ranges raises an alarm and the application serves nothing.
 */
#ifndef MPCL_APP_H
#define MPCL_APP_H

#include "mpcl_session.h"

#ifndef MPCL_CONFIG_D_BASE
#define MPCL_CONFIG_D_BASE 80
#endif
#define MPCL_CONFIG_COUNT 23
#define MPCL_DEFAULT_PORT 50241
#define MPCL_DEFAULT_TICK_US 4000u
#define MPCL_ALARM_CODE 8100        /* user alarm number the application raises on a bad configuration */

/* Controller status signals (the I/O map MotoROS reads as well): motion needs servo on, play and remote
 * mode, no alarm or error, and no E-stop (those three read 0 while pressed). */
#define MPCL_IO_ALARM_MAJOR 50010
#define MPCL_IO_ALARM_MINOR 50011
#define MPCL_IO_ALARM_SYSTEM 50012
#define MPCL_IO_ALARM_USER 50013
#define MPCL_IO_ERROR 50014
#define MPCL_IO_PLAY 50054
#define MPCL_IO_REMOTE 80011
#define MPCL_IO_SERVO_ON 50073
#define MPCL_IO_ESTOP_EXTERNAL 80025
#define MPCL_IO_ESTOP_PENDANT 80026
#define MPCL_IO_ESTOP_CONTROLLER 80027

/* Start-up: reads and checks the configuration; 0, or -1 after raising the alarm. */
int mpcl_app_configure(void);
/* The socket task's events and the clock task's cycle, callable one by one (the host build's fuzzer
 * drives them without threads). */
void mpcl_app_accepted(int fd);
int mpcl_app_received(const uint8_t *data, size_t length);   /* 1: drop the connection */
int mpcl_app_poll(void);                                     /* 1: drop the connection */
void mpcl_app_gone(const char *why);
void mpcl_app_cycle(void);

/* What the controller did, for its own status display and the host build's witness. */
typedef struct {
    mpcl_stats stats;
    int32_t offset[6];
    int32_t period_step[6];     /* the step of the latest control period, spread over its cycles */
    int32_t session_step[6];    /* the armed session's bounds: the HELLO's within the controller's */
    int32_t session_offset[6];
    uint32_t session_watchdog_ms;
    uint32_t periods;           /* control periods served while armed */
    uint32_t cycles;
    uint32_t motion_errors;     /* mpExRcsIncrementMove refusals */
    int armed, connected, configured;
    int pending;                /* a CORRECTION waits for the next period */
    int closing;                /* the connection is being dropped (a fault, STOP, or a failed send) */
    char config_error[MPCL_TEXT];
} mpcl_app_status;
void mpcl_app_read_status(mpcl_app_status *out);

/* The tasks. */
void mpcl_server_task(int, int, int, int, int, int, int, int, int, int);
void mpcl_clock_task(int, int, int, int, int, int, int, int, int, int);
void mpUsrRoot(int arg1, int arg2, int arg3, int arg4, int arg5, int arg6, int arg7, int arg8, int arg9, int arg10);

#endif
