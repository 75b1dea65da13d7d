/*
 * mpcl_fuzz: random HELLO / CORRECTION streams through the MotoPlus application (mpcl_app.c, the session
 * rules and the codec) on the host layer, one stream per fresh configuration, with the interpolation
 * cycles and the controller's clock advanced between the bytes. Built with the address and undefined-
 * behaviour sanitizers (make fuzz), a crash or a sanitizer report ends the run; the invariants below are
 * checked after every cycle against the controller's own configuration, never against what a HELLO said:
 *
 *   - no cycle moves more than its share of the controller's per-period clamp and speed bound, no period
 *     more than the clamp, and the total never leaves the controller's offset bound;
 *   - nothing moves in a cycle that began disarmed or with the connection closing (a failed send: the
 *     link is lost), or in a period that began with the controller not ready;
 *   - an armed session's bounds are never wider than the controller's (no widened limit);
 *   - disarmed, the offset the application reports is what mpExRcsIncrementMove was really given;
 *   - every byte the application sends decodes as a valid frame.
 *
 * Usage: mpcl_fuzz STREAMS SEED   (prints one JSON line; exit status 1 on any violation)
 */
#include "../mpcl_app.h"
#include "mph.h"

#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

static uint64_t rng_state;

static uint64_t rnd(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return rng_state;
}

static uint32_t below(uint32_t n)
{
    return n ? (uint32_t)(rnd() % n) : 0u;
}

static int chance(uint32_t percent)
{
    return below(100u) < percent;
}

/* An int32 that matters to a limit: its edges, its overflows and random values. */
static int32_t edgy(int32_t limit)
{
    switch (below(12u)) {
    case 0: return 0;
    case 1: return 1;
    case 2: return -1;
    case 3: return limit;
    case 4: return limit == INT32_MAX ? limit : limit + 1;
    case 5: return -limit;
    case 6: return limit == INT32_MAX ? -limit : -limit - 1;
    case 7: return INT32_MAX;
    case 8: return INT32_MIN;
    case 9: return (int32_t)(rnd() & 0xFFFFFFFFu);
    default: return (int32_t)below((uint32_t)(limit > 0 ? limit : 1)) * (chance(50) ? 1 : -1);
    }
}

typedef struct {
    mpcl_limits limits;
    int32_t d[MPCL_CONFIG_COUNT];
    uint32_t cycles;
} config;

#define TICK_US 4000

static void choose_config(config *c)
{
    int i;
    int32_t scale = chance(20) ? 1 : (chance(10) ? MPCL_MAX_LIMIT : 1 + (int32_t)below(5000u));
    memset(c, 0, sizeof *c);
    c->cycles = 1u + below(4u);
    for (i = 0; i < 6; ++i) {
        c->limits.max_step[i] = 1 + (int32_t)below((uint32_t)scale);
        c->limits.max_offset[i] = c->limits.max_step[i] + (int32_t)below((uint32_t)(MPCL_MAX_LIMIT - c->limits.max_step[i]) / (chance(50) ? 1000u : 1u));
        c->limits.max_speed[i] = 1 + (int32_t)below(MPCL_MAX_LIMIT);
        c->d[i] = c->limits.max_step[i];
        c->d[6 + i] = c->limits.max_offset[i];
        c->d[12 + i] = c->limits.max_speed[i];
    }
    c->limits.period_us = c->cycles * TICK_US;
    c->limits.max_watchdog_ms = 2u * c->limits.period_us / 1000u + below(3000u);
    c->d[18] = (int32_t)c->limits.max_watchdog_ms;
    c->d[19] = (int32_t)c->cycles;
    c->d[20] = 0;
    c->d[21] = TICK_US;
    c->d[22] = 0;
}

typedef struct {
    int32_t step_bound[6];   /* per period: min(clamp, speed x period) */
    int32_t share_bound[6];  /* per cycle: the step bound spread over the period's cycles, rounded up */
} bounds;

static void derive(const config *c, bounds *b)
{
    int i;
    for (i = 0; i < 6; ++i) {
        int64_t by_speed = (int64_t)c->limits.max_speed[i] * c->limits.period_us / 1000000;
        int64_t step = by_speed < 1 ? 1 : by_speed;
        if (step > c->limits.max_step[i]) step = c->limits.max_step[i];
        b->step_bound[i] = (int32_t)step;
        b->share_bound[i] = (int32_t)((step + (int64_t)c->cycles - 1) / (int64_t)c->cycles);
    }
}

typedef struct {
    uint32_t seq;
    mpcl_hello hello;        /* the last HELLO sent: CORRECTIONs mostly match its frame */
} peer;

/* A HELLO within the controller's limits, then (often) one field pushed to an edge. */
static void make_hello(mpcl_hello *h, const config *c)
{
    uint32_t shortest = 2u * c->limits.period_us / 1000u;
    int i;
    h->period_us = c->limits.period_us;
    for (i = 0; i < 6; ++i) {
        h->max_step[i] = 1 + (int32_t)below((uint32_t)c->limits.max_step[i]);
        h->max_offset[i] = 1 + (int32_t)below((uint32_t)c->limits.max_offset[i]);
    }
    h->watchdog_ms = shortest + below(c->limits.max_watchdog_ms - shortest + 1u);
    h->frame = (uint8_t)below(4u);
    h->tool = (uint8_t)below(64u);
    h->user_frame = (uint8_t)below(64u);
    if (chance(40)) {
        uint32_t axis = below(6u);
        switch (below(7u)) {
        case 0: h->period_us = chance(50) ? (uint32_t)rnd() : h->period_us + TICK_US; break;
        case 1: h->max_step[axis] = edgy(c->limits.max_step[axis]); break;
        case 2: h->max_offset[axis] = edgy(c->limits.max_offset[axis]); break;
        case 3: h->watchdog_ms = (uint32_t)edgy((int32_t)c->limits.max_watchdog_ms); break;
        case 4: h->watchdog_ms = chance(50) ? shortest - 1u : c->limits.max_watchdog_ms + 1u; break;
        case 5: h->tool = (uint8_t)(64u + below(192u)); break;
        default: h->user_frame = (uint8_t)(64u + below(192u)); break;
        }
    }
}

static size_t make_frame(peer *p, const config *c, uint8_t *out, size_t capacity)
{
    mpcl_frame f;
    int i, n;
    memset(&f, 0, sizeof f);
    switch (p->seq == 0u && chance(85) ? 0u : below(16u)) {
    case 0:
        f.type = MPCL_HELLO;
        make_hello(&f.body.hello, c);
        p->hello = f.body.hello;
        break;
    case 1:
        f.type = (uint8_t)(MPCL_STATE + below(4u));  /* STATE, HEARTBEAT, STOP or FAULT */
        if (f.type == MPCL_FAULT) {
            f.body.fault.code = (uint32_t)rnd();
            f.body.fault.length = (uint16_t)below(MPCL_MAX_FAULT_TEXT + 1u);
            for (i = 0; i < f.body.fault.length; ++i) f.body.fault.text[i] = (uint8_t)rnd();
        }
        break;
    default:
        f.type = MPCL_CORRECTION;
        for (i = 0; i < 6; ++i) {
            int64_t m = p->hello.max_step[i];
            if (m < 1 || m > c->limits.max_step[i]) m = c->limits.max_step[i];
            f.body.correction.increment[i] = chance(60) ? (int32_t)((int64_t)below((uint32_t)(2 * m + 1)) - m)
                                                        : edgy(c->limits.max_step[i]);
        }
        f.body.correction.frame = chance(95) ? p->hello.frame : (uint8_t)below(4u);
        f.body.correction.tool = chance(95) ? p->hello.tool : (uint8_t)below(256u);
        f.body.correction.user_frame = chance(95) ? p->hello.user_frame : (uint8_t)below(256u);
        break;
    }
    switch (below(50u)) {
    case 0: f.seq = p->seq; break;                       /* repeated */
    case 1: f.seq = p->seq - below(5u); break;           /* old */
    case 2: f.seq = p->seq + 2u + below(6u); break;      /* a gap, or within the allowed one */
    case 3: f.seq = (uint32_t)rnd(); break;
    default: f.seq = p->seq + 1u; break;
    }
    p->seq = f.seq;
    f.ack = (uint32_t)rnd();
    n = mpcl_encode(&f, out, capacity);
    return n > 0 ? (size_t)n : 0u;
}

/* Bit flips, a wrong length or garbage; `reseal` recomputes the checksum so the deeper rules are reached. */
static size_t mutate(uint8_t *frame, size_t length, size_t capacity)
{
    size_t k;
    switch (below(4u)) {
    case 0:
        for (k = 0; k < 1u + below(4u); ++k) frame[below((uint32_t)length)] ^= (uint8_t)(1u << below(8u));
        break;
    case 1:
        for (k = 4; k + 4 < length; ++k) if (chance(10)) frame[k] = (uint8_t)rnd();
        break;
    case 2:
        length = below((uint32_t)length);
        break;
    default:
        length = below((uint32_t)capacity);
        for (k = 0; k < length; ++k) frame[k] = (uint8_t)rnd();
        break;
    }
    if (length >= 24u && chance(50)) {
        uint32_t crc = mpcl_crc32(frame + 4, length - 8u);
        frame[length - 4] = (uint8_t)(crc & 0xFFu);
        frame[length - 3] = (uint8_t)((crc >> 8) & 0xFFu);
        frame[length - 2] = (uint8_t)((crc >> 16) & 0xFFu);
        frame[length - 1] = (uint8_t)(crc >> 24);
    }
    return length;
}

static struct {
    uint64_t streams, configs_refused, frames, bytes, cycles, moving_cycles, sessions, faults, clamped;
    uint64_t fault_codes[8], violations;
    char first_violation[256];
} totals;

static void violation(const char *what, long value, long bound)
{
    if (!totals.violations) {
        snprintf(totals.first_violation, sizeof totals.first_violation, "stream %llu: %s %ld beyond %ld",
                 (unsigned long long)totals.streams, what, value, bound);
    }
    totals.violations++;
}

typedef struct {
    const config *c;
    bounds b;
    int64_t moved[6];
    int64_t period_moved[6];
    int ready, period_ready;
    mpcl_reader sent;       /* what the application sent, decoded */
    int out_fd;
} run;

static void drain(run *r)
{
    uint8_t buffer[4096];
    mpcl_frame frame;
    ssize_t n;
    while ((n = read(r->out_fd, buffer, sizeof buffer)) > 0) {
        size_t used = 0;
        while (used < (size_t)n) {
            int got;
            used += mpcl_reader_feed(&r->sent, buffer + used, (size_t)n - used);
            while ((got = mpcl_reader_next(&r->sent, &frame)) > 0) {}
            if (got < 0) {
                violation("malformed frame sent, rule", got, 0);
                mpcl_reader_init(&r->sent);
                break;
            }
        }
    }
}

static void cycle(run *r)
{
    mpcl_app_status before, after;
    int32_t inc[6];
    uint32_t phase;
    int i, moving = 0;
    mpcl_app_read_status(&before);
    phase = (before.cycles + 1u) % r->c->cycles;
    if (phase == 0u) {  /* a period begins: its sums restart */
        memset(r->period_moved, 0, sizeof r->period_moved);
        r->period_ready = r->ready;
    }
    mpcl_app_cycle();
    mph_take_increment(inc);
    mpcl_app_read_status(&after);
    totals.cycles++;
    for (i = 0; i < 6; ++i) {
        moving |= inc[i] != 0;
        r->moved[i] += inc[i];
        r->period_moved[i] += inc[i];
        if (inc[i] > r->b.share_bound[i] || inc[i] < -r->b.share_bound[i]) violation("cycle share", inc[i], r->b.share_bound[i]);
        if (r->period_moved[i] > r->b.step_bound[i] || r->period_moved[i] < -(int64_t)r->b.step_bound[i])
            violation("period step", (long)r->period_moved[i], r->b.step_bound[i]);
        if (r->moved[i] > r->c->limits.max_offset[i] || r->moved[i] < -(int64_t)r->c->limits.max_offset[i])
            violation("total offset", (long)r->moved[i], r->c->limits.max_offset[i]);
    }
    if (moving) {
        totals.moving_cycles++;
        if (!before.armed) violation("motion in a cycle that began disarmed", 1, 0);
        if (before.closing) violation("motion in a cycle that began with the connection closing", 1, 0);
        if (!r->period_ready) violation("motion in a period that began not ready", 1, 0);
    }
    if (!after.armed) {  /* nothing is left to hand out: the offset it reports is what really moved */
        for (i = 0; i < 6; ++i) {
            if (after.offset[i] != r->moved[i]) violation("reported offset beside what moved", after.offset[i], (long)r->moved[i]);
        }
    } else {
        for (i = 0; i < 6; ++i) {
            if (after.session_step[i] > r->b.step_bound[i] || after.session_step[i] < 1)
                violation("widened session step", after.session_step[i], r->b.step_bound[i]);
            if (after.session_offset[i] > r->c->limits.max_offset[i] || after.session_offset[i] < 1)
                violation("widened session offset", after.session_offset[i], r->c->limits.max_offset[i]);
        }
        if (after.session_watchdog_ms > r->c->limits.max_watchdog_ms)
            violation("widened watchdog", (long)after.session_watchdog_ms, (long)r->c->limits.max_watchdog_ms);
    }
    drain(r);
}

static void one_stream(void)
{
    config c;
    run r;
    peer p;
    int pair[2], i, events;
    mpcl_app_status status;
    choose_config(&c);
    mph_reset();
    mph_virtual_clock((uint32_t)rnd());  /* anywhere, including just before the 32-bit wrap */
    if (chance(3)) {  /* a configuration the integrator got wrong: refused, nothing served */
        int k = (int)below(MPCL_CONFIG_COUNT);
        c.d[k] = edgy(c.d[k]);
    }
    for (i = 0; i < MPCL_CONFIG_COUNT; ++i) mph_set_var_d(MPCL_CONFIG_D_BASE + i, c.d[i]);
    if (mpcl_app_configure() != 0) {
        totals.configs_refused++;
        return;
    }
    mpcl_app_read_status(&status);
    /* what was accepted is within the documented ranges, whatever the variable said */
    for (i = 0; i < 6; ++i) {
        if (c.d[i] < 1 || c.d[i] > MPCL_MAX_LIMIT) violation("accepted a max_step of", c.d[i], MPCL_MAX_LIMIT);
        if (c.d[6 + i] < 1 || c.d[6 + i] > MPCL_MAX_LIMIT) violation("accepted a max_offset of", c.d[6 + i], MPCL_MAX_LIMIT);
        if (c.d[12 + i] < 1 || c.d[12 + i] > MPCL_MAX_LIMIT) violation("accepted a max_speed of", c.d[12 + i], MPCL_MAX_LIMIT);
    }
    c.cycles = (uint32_t)c.d[19];
    c.limits.period_us = c.cycles * TICK_US;
    for (i = 0; i < 6; ++i) {
        c.limits.max_step[i] = c.d[i];
        c.limits.max_offset[i] = c.d[6 + i];
        c.limits.max_speed[i] = c.d[12 + i];
    }
    c.limits.max_watchdog_ms = (uint32_t)c.d[18];
    memset(&r, 0, sizeof r);
    r.c = &c;
    derive(&c, &r.b);
    r.ready = r.period_ready = 1;
    mpcl_reader_init(&r.sent);
    if (socketpair(AF_UNIX, SOCK_STREAM, 0, pair) != 0) {
        perror("socketpair");
        exit(2);
    }
    fcntl(pair[1], F_SETFL, O_NONBLOCK);
    r.out_fd = pair[1];
    memset(&p, 0, sizeof p);
    mpcl_app_accepted(pair[0]);
    events = 1 + (int)below(40u);
    for (i = 0; i < events; ++i) {
        uint8_t frame[MPCL_MAX_FRAME + 64];
        size_t length = make_frame(&p, &c, frame, sizeof frame), sent = 0;
        int k, closed = 0;
        if (chance(3)) length = mutate(frame, length, sizeof frame);
        totals.frames++;
        totals.bytes += length;
        while (sent < length && !closed) {  /* in random pieces, cycles and time passing between them */
            size_t piece = 1u + below((uint32_t)(length - sent));
            closed = mpcl_app_received(frame + sent, piece);
            sent += piece;
            if (chance(10)) cycle(&r);
        }
        drain(&r);
        if (closed) break;
        if (chance(5)) {
            r.ready = !r.ready || chance(50);
            mph_set_io(MPCL_IO_SERVO_ON, r.ready);
        }
        if (chance(3)) mph_set_motion_error(chance(50) ? 0 : -1);
        if (chance(2)) mph_set_net_faults(0.0, 0u, 1u + below(4u), rnd());  /* the link breaks at a later send */
        for (k = (int)below(6u); k > 0; --k) {
            mph_advance_ms(chance(5) ? below(3000u) : below(c.cycles * 4u + 1u));
            cycle(&r);
        }
        if (mpcl_app_poll()) break;
    }
    for (i = (int)below(8u); i > 0; --i) cycle(&r);  /* the session's last periods */
    mpcl_app_read_status(&status);
    totals.sessions += status.stats.sessions;
    totals.faults += status.stats.faults;
    totals.clamped += status.stats.clamped;
    if (status.stats.faults) totals.fault_codes[status.stats.last_fault_code < 8u ? status.stats.last_fault_code : 0]++;
    mpcl_app_gone("the stream ended");
    close(pair[0]);
    close(pair[1]);
    mph_set_motion_error(0);
}

int main(int argc, char **argv)
{
    uint64_t streams, n;
    if (argc != 3) {
        fprintf(stderr, "usage: %s STREAMS SEED\n", argv[0]);
        return 2;
    }
    streams = strtoull(argv[1], NULL, 10);
    rng_state = strtoull(argv[2], NULL, 10) * 2654435761u + 88172645463325252u;
    for (n = 0; n < streams; ++n) {
        totals.streams = n;
        one_stream();
    }
    printf("{\"streams\": %llu, \"configs_refused\": %llu, \"frames\": %llu, \"bytes\": %llu, \"cycles\": %llu, "
           "\"moving_cycles\": %llu, \"sessions\": %llu, \"faults\": %llu, \"clamped_periods\": %llu, "
           "\"faults_by_code\": [%llu, %llu, %llu, %llu, %llu, %llu, %llu, %llu], \"violations\": %llu, "
           "\"first_violation\": \"%s\"}\n",
           (unsigned long long)streams, (unsigned long long)totals.configs_refused,
           (unsigned long long)totals.frames, (unsigned long long)totals.bytes, (unsigned long long)totals.cycles,
           (unsigned long long)totals.moving_cycles, (unsigned long long)totals.sessions,
           (unsigned long long)totals.faults, (unsigned long long)totals.clamped,
           (unsigned long long)totals.fault_codes[0], (unsigned long long)totals.fault_codes[1],
           (unsigned long long)totals.fault_codes[2], (unsigned long long)totals.fault_codes[3],
           (unsigned long long)totals.fault_codes[4], (unsigned long long)totals.fault_codes[5],
           (unsigned long long)totals.fault_codes[6], (unsigned long long)totals.fault_codes[7],
           (unsigned long long)totals.violations, totals.first_violation);
    return totals.violations ? 1 : 0;
}
