/* mpcl: see mpcl.h. Every check here mirrors one in profile_pose_ros/core/motoplus_protocol.py, in the
 * same order, so both sides refuse the same bytes for the same reason. */
#include "mpcl.h"

#include <string.h>

static const uint8_t MAGIC[4] = {'M', 'P', 'C', 'L'};

enum { HELLO_SIZE = 4 + 24 + 24 + 4 + 4, CORRECTION_SIZE = 24 + 4, STATE_SIZE = 4 + 24 + 24 + 4 + 4 + 8,
       FAULT_HEAD_SIZE = 6 };

/* ---------------------------------------------------------------- little-endian fields, byte by byte */

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static int32_t get_i32(const uint8_t *p)
{
    uint32_t u = get_u32(p);
    /* two's complement without implementation-defined conversion */
    return u <= 0x7FFFFFFFu ? (int32_t)u : (int32_t)(u - 0x80000000u) - 0x7FFFFFFF - 1;
}

static uint64_t get_u64(const uint8_t *p)
{
    return (uint64_t)get_u32(p) | ((uint64_t)get_u32(p + 4) << 32);
}

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}

static void put_i32(uint8_t *p, int32_t v)
{
    put_u32(p, (uint32_t)v);  /* conversion to unsigned is defined: modulo 2^32 */
}

static void put_u64(uint8_t *p, uint64_t v)
{
    put_u32(p, (uint32_t)(v & 0xFFFFFFFFu));
    put_u32(p + 4, (uint32_t)(v >> 32));
}

static void get_six(const uint8_t *p, int32_t out[6])
{
    int i;
    for (i = 0; i < 6; ++i) out[i] = get_i32(p + 4 * i);
}

static void put_six(uint8_t *p, const int32_t v[6])
{
    int i;
    for (i = 0; i < 6; ++i) put_i32(p + 4 * i, v[i]);
}

/* ---------------------------------------------------------------- CRC-32 */

uint32_t mpcl_crc32(const uint8_t *data, size_t length)
{
    /* a nibble table: 64 bytes of constants, fast enough for 1 KB frames at 250 Hz */
    static const uint32_t table[16] = {
        0x00000000u, 0x1DB71064u, 0x3B6E20C8u, 0x26D930ACu, 0x76DC4190u, 0x6B6B51F4u, 0x4DB26158u, 0x5005713Cu,
        0xEDB88320u, 0xF00F9344u, 0xD6D6A3E8u, 0xCB61B38Cu, 0x9B64C2B0u, 0x86D3D2D4u, 0xA00AE278u, 0xBDBDF21Cu};
    uint32_t crc = 0xFFFFFFFFu;
    size_t i;
    for (i = 0; i < length; ++i) {
        crc ^= data[i];
        crc = (crc >> 4) ^ table[crc & 0x0Fu];
        crc = (crc >> 4) ^ table[crc & 0x0Fu];
    }
    return crc ^ 0xFFFFFFFFu;
}

/* ---------------------------------------------------------------- decode */

static int known_coord(uint8_t frame)
{
    return frame <= MPCL_FRAME_USER;
}

static int decode_body(uint8_t type, const uint8_t *p, size_t size, mpcl_frame *out)
{
    switch (type) {
    case MPCL_HELLO: {
        mpcl_hello *h = &out->body.hello;
        int i;
        if (size != HELLO_SIZE) return MPCL_E_SIZE;
        h->period_us = get_u32(p);
        get_six(p + 4, h->max_step);
        get_six(p + 28, h->max_offset);
        h->watchdog_ms = get_u32(p + 52);
        h->frame = p[56];
        h->tool = p[57];
        h->user_frame = p[58];
        if (!known_coord(h->frame)) return MPCL_E_FRAME;
        if (h->period_us == 0) return MPCL_E_LIMITS;
        for (i = 0; i < 6; ++i)
            if (h->max_step[i] < 0 || h->max_offset[i] < 0) return MPCL_E_LIMITS;
        return MPCL_OK;
    }
    case MPCL_CORRECTION: {
        mpcl_correction *c = &out->body.correction;
        if (size != CORRECTION_SIZE) return MPCL_E_SIZE;
        get_six(p, c->increment);
        c->frame = p[24];
        c->tool = p[25];
        c->user_frame = p[26];
        return known_coord(c->frame) ? MPCL_OK : MPCL_E_FRAME;
    }
    case MPCL_STATE: {
        mpcl_state *s = &out->body.state;
        if (size != STATE_SIZE) return MPCL_E_SIZE;
        s->echoed_seq = get_u32(p);
        get_six(p + 4, s->pose);
        get_six(p + 28, s->offset);
        s->status = get_u32(p + 52);
        s->error_code = get_u32(p + 56);
        s->time_us = get_u64(p + 60);
        return MPCL_OK;
    }
    case MPCL_HEARTBEAT:
    case MPCL_STOP:
        return size == 0 ? MPCL_OK : MPCL_E_SIZE;
    case MPCL_FAULT: {
        mpcl_fault *f = &out->body.fault;
        if (size < FAULT_HEAD_SIZE) return MPCL_E_SIZE;
        f->code = get_u32(p);
        f->length = (uint16_t)(p[4] | (p[5] << 8));
        if (size != FAULT_HEAD_SIZE + (size_t)f->length || f->length > MPCL_MAX_FAULT_TEXT) return MPCL_E_TEXT;
        memcpy(f->text, p + FAULT_HEAD_SIZE, f->length);
        return MPCL_OK;
    }
    default:
        return MPCL_E_TYPE;
    }
}

int mpcl_decode(const uint8_t *inner, size_t length, mpcl_frame *out)
{
    if (length < MPCL_MIN_FRAME) return MPCL_E_SHORT;
    if (mpcl_crc32(inner, length - 4) != get_u32(inner + length - 4)) return MPCL_E_CHECKSUM;
    if (memcmp(inner, MAGIC, 4) != 0) return MPCL_E_MAGIC;
    if (inner[4] != MPCL_VERSION) return MPCL_E_VERSION;
    memset(out, 0, sizeof *out);
    out->type = inner[5];
    out->seq = get_u32(inner + 8);
    out->ack = get_u32(inner + 12);
    return decode_body(out->type, inner + MPCL_HEADER_SIZE, length - MPCL_MIN_FRAME, out);
}

/* ---------------------------------------------------------------- encode */

static size_t encode_body(const mpcl_frame *frame, uint8_t *p)
{
    switch (frame->type) {
    case MPCL_HELLO: {
        const mpcl_hello *h = &frame->body.hello;
        put_u32(p, h->period_us);
        put_six(p + 4, h->max_step);
        put_six(p + 28, h->max_offset);
        put_u32(p + 52, h->watchdog_ms);
        p[56] = h->frame;
        p[57] = h->tool;
        p[58] = h->user_frame;
        p[59] = 0;
        return HELLO_SIZE;
    }
    case MPCL_CORRECTION: {
        const mpcl_correction *c = &frame->body.correction;
        put_six(p, c->increment);
        p[24] = c->frame;
        p[25] = c->tool;
        p[26] = c->user_frame;
        p[27] = 0;
        return CORRECTION_SIZE;
    }
    case MPCL_STATE: {
        const mpcl_state *s = &frame->body.state;
        put_u32(p, s->echoed_seq);
        put_six(p + 4, s->pose);
        put_six(p + 28, s->offset);
        put_u32(p + 52, s->status);
        put_u32(p + 56, s->error_code);
        put_u64(p + 60, s->time_us);
        return STATE_SIZE;
    }
    case MPCL_FAULT: {
        const mpcl_fault *f = &frame->body.fault;
        uint16_t length = f->length > MPCL_MAX_FAULT_TEXT ? (uint16_t)MPCL_MAX_FAULT_TEXT : f->length;
        put_u32(p, f->code);
        put_u16(p + 4, length);
        memcpy(p + FAULT_HEAD_SIZE, f->text, length);
        return FAULT_HEAD_SIZE + (size_t)length;
    }
    default:  /* HEARTBEAT, STOP */
        return 0;
    }
}

int mpcl_encode(const mpcl_frame *frame, uint8_t *out, size_t capacity)
{
    /* the largest body is a full FAULT; build in place only when it surely fits */
    enum { LARGEST = MPCL_MIN_FRAME + FAULT_HEAD_SIZE + MPCL_MAX_FAULT_TEXT };
    uint8_t inner[LARGEST];
    size_t length;
    if (frame->type < MPCL_HELLO || frame->type > MPCL_FAULT) return MPCL_E_CAPACITY;
    memcpy(inner, MAGIC, 4);
    inner[4] = MPCL_VERSION;
    inner[5] = frame->type;
    put_u16(inner + 6, 0);
    put_u32(inner + 8, frame->seq);
    put_u32(inner + 12, frame->ack);
    length = MPCL_HEADER_SIZE + encode_body(frame, inner + MPCL_HEADER_SIZE);
    put_u32(inner + length, mpcl_crc32(inner, length));
    length += 4;
    if (capacity < 4 + length) return MPCL_E_CAPACITY;
    put_u32(out, (uint32_t)length);
    memcpy(out + 4, inner, length);
    return (int)(4 + length);
}

/* ---------------------------------------------------------------- stream */

void mpcl_reader_init(mpcl_reader *reader)
{
    reader->used = 0;
    reader->failed = MPCL_OK;
}

size_t mpcl_reader_feed(mpcl_reader *reader, const uint8_t *data, size_t length)
{
    size_t room = sizeof reader->buffer - reader->used;
    size_t taken = length < room ? length : room;
    if (reader->failed != MPCL_OK) return length;  /* the stream is dead: nothing will be read from it */
    memcpy(reader->buffer + reader->used, data, taken);
    reader->used += taken;
    return taken;
}

int mpcl_reader_next(mpcl_reader *reader, mpcl_frame *out)
{
    uint32_t length;
    int result;
    if (reader->failed != MPCL_OK) return reader->failed;
    if (reader->used < 4) return 0;
    length = get_u32(reader->buffer);
    if (length < MPCL_MIN_FRAME || length > MPCL_MAX_FRAME) return reader->failed = MPCL_E_LENGTH;
    if (reader->used < 4u + length) return 0;
    result = mpcl_decode(reader->buffer + 4, length, out);
    reader->used -= 4u + length;
    memmove(reader->buffer, reader->buffer + 4 + length, reader->used);
    if (result != MPCL_OK) return reader->failed = result;
    return 1;
}

/* ---------------------------------------------------------------- rules */

enum mpcl_sequence mpcl_sequence_verdict(uint32_t last_seq, uint32_t seq)
{
    if (seq <= last_seq) return MPCL_SEQ_OLD;
    return seq - last_seq > MPCL_MAX_SEQ_GAP + 1u ? MPCL_SEQ_GAP : MPCL_SEQ_NEW;
}

int mpcl_clamp(int32_t increment[6], const int32_t limit[6])
{
    int i, cut = 0;
    for (i = 0; i < 6; ++i) {
        if (increment[i] > limit[i]) {
            increment[i] = limit[i];
            cut = 1;
        } else if (increment[i] < -limit[i]) {
            increment[i] = -limit[i];
            cut = 1;
        }
    }
    return cut;
}

const char *mpcl_error_name(int error)
{
    static const char *const names[] = {"ok", "length", "short", "checksum", "magic", "version", "type", "size",
                                        "frame", "limits", "text", "capacity"};
    return error <= 0 && error >= MPCL_E_CAPACITY ? names[-error] : "unknown";
}
