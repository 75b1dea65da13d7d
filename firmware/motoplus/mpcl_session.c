/* mpcl_session: see mpcl_session.h. The rules are docs/motoplus_protocol.md's; every value from the
 * network is range-checked before it is used. */
#include "mpcl_session.h"

#include <stdio.h>
#include <string.h>

static const char *const AXES[6] = {"x", "y", "z", "rx", "ry", "rz"};

static void text(char *dst, const char *src)
{
    size_t n = strlen(src);
    if (n >= MPCL_TEXT) n = MPCL_TEXT - 1u;
    memcpy(dst, src, n);
    dst[n] = '\0';
}

static void emit(mpcl_session *s, const mpcl_frame *frame)
{
    int n = mpcl_encode(frame, s->out + s->out_len, sizeof s->out - s->out_len);
    if (n < 0) {
        s->stats.dropped_frames++;  /* the owner has not drained `out`: a STATE more or less, never motion */
        return;
    }
    s->out_len += (size_t)n;
}

static void emit_state(mpcl_session *s, uint32_t status, uint64_t time_us)
{
    mpcl_frame f;
    memset(&f, 0, sizeof f);
    f.type = MPCL_STATE;
    f.seq = ++s->my_seq;
    f.ack = s->peer_seq;
    f.body.state.echoed_seq = s->applied_seq;
    memcpy(f.body.state.pose, s->pose, sizeof s->pose);
    memcpy(f.body.state.offset, s->offset, sizeof s->offset);
    f.body.state.status = status;
    f.body.state.time_us = time_us;
    emit(s, &f);
    s->stats.states++;
}

static void end_session(mpcl_session *s, const char *why)
{
    text(s->stats.session_end, why);
    s->stats.sessions_ended++;
    s->armed = 0;
    s->pending = 0;
    s->close = 1;
}

/* Latch: disarm, tell the peer why, and have the connection dropped. */
static void fault(mpcl_session *s, uint32_t code, const char *why)
{
    mpcl_frame f;
    char reason[MPCL_TEXT];
    size_t n = strlen(why);
    s->stats.faults++;
    s->stats.last_fault_code = code;
    text(s->stats.last_fault, why);
    s->armed = 0;  /* disarmed before the peer hears why */
    memset(&f, 0, sizeof f);
    f.type = MPCL_FAULT;
    f.seq = ++s->my_seq;
    f.ack = s->peer_seq;
    f.body.fault.code = code;
    if (n > MPCL_MAX_FAULT_TEXT) n = MPCL_MAX_FAULT_TEXT;
    f.body.fault.length = (uint16_t)n;
    memcpy(f.body.fault.text, why, n);
    emit(s, &f);
    snprintf(reason, sizeof reason, "FAULT %lu: %s", (unsigned long)code, why);
    end_session(s, reason);
}

int mpcl_limits_check(const mpcl_limits *limits, char *why, size_t capacity)
{
    int i;
    for (i = 0; i < 6; ++i) {
        const int32_t values[3] = {limits->max_step[i], limits->max_offset[i], limits->max_speed[i]};
        static const char *const names[3] = {"max_step", "max_offset", "max_speed"};
        int k;
        for (k = 0; k < 3; ++k) {
            if (values[k] < 1 || values[k] > MPCL_MAX_LIMIT) {
                snprintf(why, capacity, "controller %s[%s] = %ld: must be 1..%ld", names[k], AXES[i],
                         (long)values[k], (long)MPCL_MAX_LIMIT);
                return -1;
            }
        }
    }
    if (limits->period_us < 1000u || limits->period_us > 1000000u) {
        snprintf(why, capacity, "controller period %lu us: must be 1000..1000000", (unsigned long)limits->period_us);
        return -1;
    }
    if (limits->max_watchdog_ms < 2u * limits->period_us / 1000u || limits->max_watchdog_ms > 60000u) {
        snprintf(why, capacity, "controller max_watchdog %lu ms: must be two periods..60000",
                 (unsigned long)limits->max_watchdog_ms);
        return -1;
    }
    return 0;
}

void mpcl_session_init(mpcl_session *s, const mpcl_limits *limits)
{
    memset(s, 0, sizeof *s);
    s->limits = *limits;
}

void mpcl_session_open(mpcl_session *s, uint32_t now_ms)
{
    s->connected = 1;
    s->armed = 0;
    s->close = 0;
    s->lost = NULL;
    s->pending = 0;
    s->connected_ms = s->last_frame_ms = now_ms;
    s->peer_seq = 0;
    s->out_len = 0;
    mpcl_reader_init(&s->reader);
}

/* The bounds a HELLO asks for, each within the controller's; 0, or a FAULT (limit) naming the field. */
static int arm(mpcl_session *s, const mpcl_frame *frame, uint32_t now_ms)
{
    const mpcl_hello *h = &frame->body.hello;
    const mpcl_limits *c = &s->limits;
    char why[MPCL_TEXT];
    uint32_t shortest = 2u * c->period_us / 1000u;
    int i;
    if (h->period_us != c->period_us) {
        snprintf(why, sizeof why, "HELLO asks for a %lu us period; this controller runs %lu us",
                 (unsigned long)h->period_us, (unsigned long)c->period_us);
        fault(s, MPCL_FAULT_PROTOCOL, why);
        return -1;
    }
    for (i = 0; i < 6; ++i) {
        if (h->max_step[i] < 1 || h->max_step[i] > c->max_step[i]) {
            snprintf(why, sizeof why, "HELLO max_step[%d] = %ld: must be 1..%ld (the controller's limit)", i,
                     (long)h->max_step[i], (long)c->max_step[i]);
            fault(s, MPCL_FAULT_LIMIT, why);
            return -1;
        }
        if (h->max_offset[i] < 1 || h->max_offset[i] > c->max_offset[i]) {
            snprintf(why, sizeof why, "HELLO max_offset[%d] = %ld: must be 1..%ld (the controller's limit)", i,
                     (long)h->max_offset[i], (long)c->max_offset[i]);
            fault(s, MPCL_FAULT_LIMIT, why);
            return -1;
        }
    }
    if (h->watchdog_ms < shortest || h->watchdog_ms > c->max_watchdog_ms) {
        snprintf(why, sizeof why, "HELLO watchdog_ms = %lu: must be %lu..%lu (two periods to the controller's limit)",
                 (unsigned long)h->watchdog_ms, (unsigned long)shortest, (unsigned long)c->max_watchdog_ms);
        fault(s, MPCL_FAULT_LIMIT, why);
        return -1;
    }
    if (h->tool > MPCL_MAX_TOOL || h->user_frame > MPCL_MAX_USER_FRAME) {
        snprintf(why, sizeof why, "HELLO tool %u, user frame %u: each must be 0..63", h->tool, h->user_frame);
        fault(s, MPCL_FAULT_LIMIT, why);
        return -1;
    }
    if (!s->ready) {
        fault(s, MPCL_FAULT_ALARM, "the controller is not ready to move (servo off, not in play or remote, or an alarm)");
        return -1;
    }
    for (i = 0; i < 6; ++i) {
        int64_t by_speed = (int64_t)c->max_speed[i] * (int64_t)c->period_us / 1000000;
        if (by_speed < 1) by_speed = 1;
        s->step[i] = by_speed < h->max_step[i] ? (int32_t)by_speed : h->max_step[i];
        s->offset_bound[i] = h->max_offset[i];
    }
    s->watchdog_ms = h->watchdog_ms;
    s->frame = h->frame;
    s->tool = h->tool;
    s->user_frame = h->user_frame;
    s->peer_seq = frame->seq;
    s->last_frame_ms = now_ms;
    s->applied_seq = 0;
    s->periods_without = 0;
    s->pending = 0;
    s->cut = 0;
    s->armed = 1;
    s->stats.sessions++;
    return 0;
}

static void handle(mpcl_session *s, const mpcl_frame *frame, uint32_t now_ms)
{
    char why[MPCL_TEXT];
    if (frame->type == MPCL_HELLO) {
        if (s->armed) {
            fault(s, MPCL_FAULT_PROTOCOL, "a second HELLO in one session (limits are set once, at arming)");
        } else if (arm(s, frame, now_ms) == 0) {
            emit_state(s, MPCL_ARMED, 0u);
        }
        return;
    }
    if (frame->type == MPCL_STATE) {
        fault(s, MPCL_FAULT_PROTOCOL, "STATE is the controller's frame");
        return;
    }
    if (!s->armed) {
        if (frame->type == MPCL_CORRECTION) fault(s, MPCL_FAULT_NOT_ARMED, "CORRECTION before HELLO");
        return;  /* HEARTBEAT, STOP or FAULT with no session: nothing to end */
    }
    switch (mpcl_sequence_verdict(s->peer_seq, frame->seq)) {
    case MPCL_SEQ_OLD:
        return;  /* old or repeated: ignored */
    case MPCL_SEQ_GAP:
        snprintf(why, sizeof why, "sequence jumped from %lu to %lu", (unsigned long)s->peer_seq,
                 (unsigned long)frame->seq);
        fault(s, MPCL_FAULT_SEQUENCE_GAP, why);
        return;
    case MPCL_SEQ_NEW:
        break;
    }
    s->peer_seq = frame->seq;
    s->last_frame_ms = now_ms;
    switch (frame->type) {
    case MPCL_CORRECTION: {
        const mpcl_correction *c = &frame->body.correction;
        if (c->frame != s->frame || c->tool != s->tool || c->user_frame != s->user_frame) {
            snprintf(why, sizeof why, "CORRECTION in frame %u tool %u user frame %u; the session's are %u %u %u",
                     c->frame, c->tool, c->user_frame, s->frame, s->tool, s->user_frame);
            fault(s, MPCL_FAULT_PROTOCOL, why);
            return;
        }
        s->stats.replaced += (uint32_t)s->pending;  /* overwritten before a period applied it */
        s->pending = 1;
        s->pending_seq = frame->seq;
        memcpy(s->pending_increment, c->increment, sizeof s->pending_increment);
        return;
    }
    case MPCL_STOP:
        end_session(s, "STOP");
        return;
    case MPCL_FAULT:
        snprintf(why, sizeof why, "bridge reported: %.*s", (int)frame->body.fault.length,
                 (const char *)frame->body.fault.text);
        fault(s, frame->body.fault.code, why);
        return;
    default:
        return;  /* HEARTBEAT: only keeps the watchdog fed */
    }
}

/* Frames are still taken: no close pending, or the link lost while the session lasts (its STOP counts). */
static int taking(const mpcl_session *s)
{
    return !s->close || (s->lost != NULL && s->armed);
}

int mpcl_session_feed(mpcl_session *s, const uint8_t *data, size_t length, uint32_t now_ms)
{
    mpcl_frame frame;
    char why[MPCL_TEXT];
    while (taking(s)) {
        size_t taken = mpcl_reader_feed(&s->reader, data, length);
        int got;
        data += taken;
        length -= taken;
        while (taking(s) && (got = mpcl_reader_next(&s->reader, &frame)) != 0) {
            if (got < 0) {
                snprintf(why, sizeof why, "protocol error: %s", mpcl_error_name(got));
                fault(s, MPCL_FAULT_PROTOCOL, why);
                return s->close;
            }
            handle(s, &frame, now_ms);
        }
        if (length == 0u) break;
    }
    return s->close;
}

int mpcl_session_poll(mpcl_session *s, uint32_t now_ms)
{
    if (s->connected && !s->armed && !s->close && now_ms - s->connected_ms > MPCL_HELLO_TIMEOUT_MS) {
        s->stats.idle_closed++;
        text(s->stats.session_end, "no HELLO within 1 s of connecting");
        s->close = 1;
    }
    return s->close;
}

int mpcl_session_period(mpcl_session *s, uint32_t now_ms, uint64_t time_us, const int32_t pose[6], int ready,
                        int32_t step[6])
{
    char why[MPCL_TEXT];
    uint32_t status = MPCL_ARMED;
    int i, moving = 0;
    memset(step, 0, 6 * sizeof step[0]);
    memcpy(s->pose, pose, sizeof s->pose);
    s->ready = ready;
    if (!s->armed || s->close) return s->close;
    if (now_ms - s->last_frame_ms > s->watchdog_ms) {
        snprintf(why, sizeof why, "no frame for %lu ms", (unsigned long)(now_ms - s->last_frame_ms));
        fault(s, MPCL_FAULT_WATCHDOG, why);
        return s->close;
    }
    if (!ready) {
        fault(s, MPCL_FAULT_ALARM, "the controller stopped being ready to move (servo off, mode or alarm)");
        return s->close;
    }
    if (s->pending) {
        int32_t increment[6];
        int64_t total[6];
        memcpy(increment, s->pending_increment, sizeof increment);
        s->cut = mpcl_clamp(increment, s->step);
        for (i = 0; i < 6; ++i) {
            total[i] = (int64_t)s->offset[i] + increment[i];
            if (total[i] > s->offset_bound[i] || total[i] < -(int64_t)s->offset_bound[i]) {
                snprintf(why, sizeof why, "total offset %s %lld beyond %ld", AXES[i], (long long)total[i],
                         (long)s->offset_bound[i]);
                fault(s, MPCL_FAULT_LIMIT, why);
                return s->close;
            }
        }
        for (i = 0; i < 6; ++i) {
            s->offset[i] = (int32_t)total[i];
            step[i] = increment[i];
            moving |= increment[i] != 0;
        }
        s->stats.clamped += (uint32_t)s->cut;
        s->applied_seq = s->pending_seq;
        s->pending = 0;
        s->periods_without = 0;
    } else {
        s->periods_without++;
        s->cut = 0;
    }
    if (s->periods_without >= MPCL_HOLD_AFTER_PERIODS) status |= MPCL_HOLDING;
    if (s->cut) status |= MPCL_CLAMPED;
    if (moving) status |= MPCL_MOVING;
    emit_state(s, status, time_us);
    return s->close;
}

void mpcl_session_alarm(mpcl_session *s, const char *why)
{
    if (s->armed) fault(s, MPCL_FAULT_ALARM, why);
}

void mpcl_session_lost(mpcl_session *s, const char *why)
{
    if (s->lost == NULL) s->lost = why;
    s->close = 1;
}

void mpcl_session_closed(mpcl_session *s, const char *why)
{
    if (s->armed) end_session(s, s->lost != NULL ? s->lost : why);
    s->connected = 0;
    s->armed = 0;
    s->close = 0;
    s->pending = 0;
    s->out_len = 0;
}
