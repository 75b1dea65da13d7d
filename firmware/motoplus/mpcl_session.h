/*
 * mpcl_session: the controller's rules for one bridge session (docs/motoplus_protocol.md, "Rules").
 *
 * Pure C99 over the codec (mpcl.h): no MotoPlus call, no clock and no socket of its own. The application
 * (mpcl_app.c) owns those and hands in bytes, the time and the arm's pose; the session answers with the
 * frames to send, the increment to apply and whether to drop the connection. Keeping the rules here lets
 * the host build, the tests and the fuzzer run exactly the code the controller runs.
 *
 * Limits belong to the controller: mpcl_limits comes from its own configuration, never from the network;
 * a HELLO may narrow it, never widen it.
 */
#ifndef MPCL_SESSION_H
#define MPCL_SESSION_H

#include "mpcl.h"

#define MPCL_HELLO_TIMEOUT_MS 1000u   /* a connection without an accepted HELLO by then is closed */
#define MPCL_HOLD_AFTER_PERIODS 3u    /* periods without a CORRECTION before the status says HOLDING */
#define MPCL_MAX_TOOL 63u             /* tool files 0..63 */
#define MPCL_MAX_USER_FRAME 63u
#define MPCL_MAX_LIMIT 100000000      /* no configured or asked limit above 100 m (or 10000 deg) */
#define MPCL_TEXT 160u
#define MPCL_OUT_CAPACITY 1024u

typedef struct {
    int32_t max_step[6];      /* per control period: um, 0.0001 deg */
    int32_t max_offset[6];    /* total offset from where the application started */
    int32_t max_speed[6];     /* per second; bounds each period's step by speed x period */
    uint32_t max_watchdog_ms; /* the longest silence a HELLO may ask to be allowed */
    uint32_t period_us;       /* the control period: STATE once per period */
} mpcl_limits;

typedef struct {
    uint32_t sessions;        /* HELLOs accepted */
    uint32_t sessions_ended;  /* by STOP, a FAULT or the bridge leaving */
    uint32_t faults, clamped, idle_closed, replaced, states, refused_peers, dropped_frames;
    uint32_t last_fault_code;
    char last_fault[MPCL_TEXT];
    char session_end[MPCL_TEXT];   /* why the last session ended */
} mpcl_stats;

typedef struct {
    mpcl_limits limits;
    int connected, armed;
    int close;                /* the socket's owner must drop the connection (after sending `out`) */
    const char *lost;         /* sending failed (why): no motion, but what the peer sent still counts */
    int ready;                /* the controller can move (servo on, play, remote, no alarm): last period */
    uint32_t connected_ms, last_frame_ms;
    mpcl_reader reader;
    /* the session's bounds: the HELLO's, within the controller's */
    int32_t step[6], offset_bound[6];
    uint32_t watchdog_ms;
    uint8_t frame, tool, user_frame;
    uint32_t peer_seq, my_seq, applied_seq, periods_without;
    int pending, cut;
    uint32_t pending_seq;
    int32_t pending_increment[6];
    int32_t offset[6];        /* everything applied since the application started */
    int32_t pose[6];          /* as the last period read it */
    uint8_t out[MPCL_OUT_CAPACITY];
    size_t out_len;
    mpcl_stats stats;
} mpcl_session;

/* 0 when the configured limits are usable, else -1 with the reason in why. */
int mpcl_limits_check(const mpcl_limits *limits, char *why, size_t capacity);

void mpcl_session_init(mpcl_session *s, const mpcl_limits *limits);
/* A peer connected. */
void mpcl_session_open(mpcl_session *s, uint32_t now_ms);
/* Bytes from the peer; returns s->close. */
int mpcl_session_feed(mpcl_session *s, const uint8_t *data, size_t length, uint32_t now_ms);
/* Between frames: closes a connection that has not armed within MPCL_HELLO_TIMEOUT_MS; returns s->close. */
int mpcl_session_poll(mpcl_session *s, uint32_t now_ms);
/* One control period: the step to apply now (zeros unless armed with a fresh CORRECTION), and the STATE.
 * ready = 0 faults an armed session (controller alarm). Returns s->close. */
int mpcl_session_period(mpcl_session *s, uint32_t now_ms, uint64_t time_us, const int32_t pose[6], int ready,
                        int32_t step[6]);
/* The motion call failed: latch a FAULT (controller alarm). */
void mpcl_session_alarm(mpcl_session *s, const char *text);
/* Sending failed: nothing moves from now on and the owner drops the connection, but bytes already received
 * are still read (a STOP sent just before the peer left ends the session as STOP); if none ends it, the
 * drop ends it with `why`. No FAULT: nothing can tell the peer. */
void mpcl_session_lost(mpcl_session *s, const char *why);
/* The connection is gone (the peer left, or the owner dropped it). */
void mpcl_session_closed(mpcl_session *s, const char *why);

#endif
