/*
 * mpcl: the controller side of the bridge <-> MotoPlus correction protocol (docs/motoplus_protocol.md).
 *
 * Pure C99 with no allocation, no global state and no byte-order assumption (every field is assembled
 * byte by byte, so it runs on a big-endian controller CPU as well), for the MotoPlus application that
 * serves the bridge. The Python codec (profile_pose_ros/core/motoplus_protocol.py) is the reference;
 * vectors.txt, generated from it, is the shared specification both are tested against.
 */
#ifndef MPCL_H
#define MPCL_H

#include <stddef.h>
#include <stdint.h>

#define MPCL_VERSION 1u
#define MPCL_HEADER_SIZE 16u    /* magic, version, type, reserved, seq, ack */
#define MPCL_MIN_FRAME 20u      /* header + CRC-32: the smallest length a prefix may announce */
#define MPCL_MAX_FRAME 1024u    /* the largest */
#define MPCL_MAX_FAULT_TEXT 200u
#define MPCL_MAX_SEQ_GAP 3u     /* CORRECTIONs that may go missing in a row before a FAULT */

enum mpcl_type { MPCL_HELLO = 1, MPCL_CORRECTION = 2, MPCL_STATE = 3, MPCL_HEARTBEAT = 4, MPCL_STOP = 5,
                 MPCL_FAULT = 6 };
enum mpcl_coord { MPCL_FRAME_BASE = 0, MPCL_FRAME_ROBOT = 1, MPCL_FRAME_TOOL = 2, MPCL_FRAME_USER = 3 };
enum mpcl_status { MPCL_ARMED = 1, MPCL_MOVING = 2, MPCL_HOLDING = 4, MPCL_FAULTED = 8, MPCL_CLAMPED = 16 };
enum mpcl_fault_code { MPCL_FAULT_SEQUENCE_GAP = 1, MPCL_FAULT_WATCHDOG = 2, MPCL_FAULT_LIMIT = 3,
                       MPCL_FAULT_PROTOCOL = 4, MPCL_FAULT_NOT_ARMED = 5, MPCL_FAULT_STOPPED = 6,
                       MPCL_FAULT_ALARM = 7 };

/* Why a frame was refused; the same rule as the Python codec's MotoPlusProtocolError.rule. After any of
 * these on a stream the next frame boundary cannot be trusted: drop the connection. */
enum mpcl_error {
    MPCL_OK = 0,
    MPCL_E_LENGTH = -1,   /* length prefix outside MPCL_MIN_FRAME..MPCL_MAX_FRAME */
    MPCL_E_SHORT = -2,    /* fewer bytes than a header and a checksum */
    MPCL_E_CHECKSUM = -3,
    MPCL_E_MAGIC = -4,
    MPCL_E_VERSION = -5,
    MPCL_E_TYPE = -6,
    MPCL_E_SIZE = -7,     /* payload of the wrong size for its type */
    MPCL_E_FRAME = -8,    /* unknown coordinate frame */
    MPCL_E_LIMITS = -9,   /* HELLO: zero period or negative limits */
    MPCL_E_TEXT = -10,    /* FAULT: text length wrong or over MPCL_MAX_FAULT_TEXT */
    MPCL_E_CAPACITY = -11 /* encode: the output buffer is too small; or an unknown type to encode */
};

typedef struct {
    uint32_t period_us;     /* a multiple of the 4 ms interpolation clock */
    int32_t max_step[6];    /* per-cycle clamp: um, 0.0001 deg */
    int32_t max_offset[6];  /* bound on the total offset from the start pose */
    uint32_t watchdog_ms;
    uint8_t frame, tool, user_frame;
} mpcl_hello;

typedef struct {
    int32_t increment[6];   /* this cycle's move: um, 0.0001 deg (MP_COORD units) */
    uint8_t frame, tool, user_frame;
} mpcl_correction;

typedef struct {
    uint32_t echoed_seq;    /* the last CORRECTION applied */
    int32_t pose[6];
    int32_t offset[6];      /* total applied since HELLO */
    uint32_t status;        /* enum mpcl_status bits */
    uint32_t error_code;
    uint64_t time_us;       /* controller clock */
} mpcl_state;

typedef struct {
    uint32_t code;          /* enum mpcl_fault_code */
    uint16_t length;
    uint8_t text[MPCL_MAX_FAULT_TEXT];  /* UTF-8, not terminated */
} mpcl_fault;

typedef struct {
    uint8_t type;           /* enum mpcl_type */
    uint32_t seq, ack;
    union {
        mpcl_hello hello;
        mpcl_correction correction;
        mpcl_state state;
        mpcl_fault fault;
    } body;
} mpcl_frame;

/* CRC-32 as zlib computes it (IEEE 802.3, reflected). */
uint32_t mpcl_crc32(const uint8_t *data, size_t length);

/* One frame without its length prefix (the `length` bytes the prefix announced): MPCL_OK or an error. */
int mpcl_decode(const uint8_t *inner, size_t length, mpcl_frame *out);

/* The frame with its length prefix into out: the number of bytes written, or MPCL_E_CAPACITY. A FAULT's
 * text is cut at MPCL_MAX_FAULT_TEXT bytes. */
int mpcl_encode(const mpcl_frame *frame, uint8_t *out, size_t capacity);

/* Splits a TCP byte stream into frames. Failures are sticky: the connection must be dropped. */
typedef struct {
    uint8_t buffer[4u + MPCL_MAX_FRAME];
    size_t used;
    int failed;             /* MPCL_OK or the error that ended the stream */
} mpcl_reader;

void mpcl_reader_init(mpcl_reader *reader);
/* Takes as many of the bytes as fit (all of them while frames are taken out with mpcl_reader_next);
 * returns how many it took. */
size_t mpcl_reader_feed(mpcl_reader *reader, const uint8_t *data, size_t length);
/* 1: the next frame is in *out; 0: it is incomplete, feed more; negative: the stream's error. */
int mpcl_reader_next(mpcl_reader *reader, mpcl_frame *out);

/* The sequence rule for a CORRECTION after `last_seq`. */
enum mpcl_sequence { MPCL_SEQ_NEW = 0, MPCL_SEQ_OLD = 1, MPCL_SEQ_GAP = 2 };
enum mpcl_sequence mpcl_sequence_verdict(uint32_t last_seq, uint32_t seq);

/* Clamps each axis to +-limit (limit >= 0); returns 1 when anything was cut. */
int mpcl_clamp(int32_t increment[6], const int32_t limit[6]);

/* "checksum", "length", ...: the rule's name, as the Python codec and vectors.txt spell it. */
const char *mpcl_error_name(int error);

#endif
