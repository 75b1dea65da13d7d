/* Checks mpcl against vectors.txt (written by the Python codec):  ./mpcl_selftest vectors.txt
 * Each decoded frame is compared field by field, re-encoded and compared byte for byte; each stream is
 * read in one piece, byte by byte and in 7-byte pieces, which must all agree. Built with
 * -DMPCL_SELFTEST_NO_MAIN it is the shared library the Python tests drive through ctypes. */
#include "mpcl.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define MAX_VALUES 4096
#define MAX_LINE 16384

/* type, seq, ack, then the body's fields in wire order; a FAULT's text one byte per value */
int mpcl_flatten(const mpcl_frame *f, int64_t *v, size_t capacity)
{
    size_t n = 0, i;
    if (capacity < 3 + 17 + MPCL_MAX_FAULT_TEXT) return -1;
    v[n++] = f->type;
    v[n++] = f->seq;
    v[n++] = f->ack;
    switch (f->type) {
    case MPCL_HELLO:
        v[n++] = f->body.hello.period_us;
        for (i = 0; i < 6; ++i) v[n++] = f->body.hello.max_step[i];
        for (i = 0; i < 6; ++i) v[n++] = f->body.hello.max_offset[i];
        v[n++] = f->body.hello.watchdog_ms;
        v[n++] = f->body.hello.frame;
        v[n++] = f->body.hello.tool;
        v[n++] = f->body.hello.user_frame;
        break;
    case MPCL_CORRECTION:
        for (i = 0; i < 6; ++i) v[n++] = f->body.correction.increment[i];
        v[n++] = f->body.correction.frame;
        v[n++] = f->body.correction.tool;
        v[n++] = f->body.correction.user_frame;
        break;
    case MPCL_STATE:
        v[n++] = f->body.state.echoed_seq;
        for (i = 0; i < 6; ++i) v[n++] = f->body.state.pose[i];
        for (i = 0; i < 6; ++i) v[n++] = f->body.state.offset[i];
        v[n++] = f->body.state.status;
        v[n++] = f->body.state.error_code;
        v[n++] = (int64_t)f->body.state.time_us;  /* the vectors' largest, 2^64 - 1, wraps to -1 here */
        break;
    case MPCL_FAULT:
        v[n++] = f->body.fault.code;
        v[n++] = f->body.fault.length;
        for (i = 0; i < f->body.fault.length; ++i) v[n++] = f->body.fault.text[i];
        break;
    default:
        break;
    }
    return (int)n;
}

/* the inverse, for encoding what the Python side describes; -1 when the values do not make a frame */
int mpcl_unflatten(const int64_t *v, size_t n, mpcl_frame *f)
{
    static const size_t sizes[7] = {0, 3 + 17, 3 + 9, 3 + 16, 3, 3, 3 + 2};
    size_t i, k = 3;
    memset(f, 0, sizeof *f);
    if (n < 3 || v[0] < MPCL_HELLO || v[0] > MPCL_FAULT) return -1;
    if (v[0] == MPCL_FAULT ? (n < sizes[MPCL_FAULT] || n != sizes[MPCL_FAULT] + (size_t)v[4]
                                  || v[4] > (int64_t)MPCL_MAX_FAULT_TEXT)
                           : n != sizes[v[0]]) return -1;
    f->type = (uint8_t)v[0];
    f->seq = (uint32_t)v[1];
    f->ack = (uint32_t)v[2];
    switch (f->type) {
    case MPCL_HELLO:
        f->body.hello.period_us = (uint32_t)v[k++];
        for (i = 0; i < 6; ++i) f->body.hello.max_step[i] = (int32_t)v[k++];
        for (i = 0; i < 6; ++i) f->body.hello.max_offset[i] = (int32_t)v[k++];
        f->body.hello.watchdog_ms = (uint32_t)v[k++];
        f->body.hello.frame = (uint8_t)v[k++];
        f->body.hello.tool = (uint8_t)v[k++];
        f->body.hello.user_frame = (uint8_t)v[k++];
        break;
    case MPCL_CORRECTION:
        for (i = 0; i < 6; ++i) f->body.correction.increment[i] = (int32_t)v[k++];
        f->body.correction.frame = (uint8_t)v[k++];
        f->body.correction.tool = (uint8_t)v[k++];
        f->body.correction.user_frame = (uint8_t)v[k++];
        break;
    case MPCL_STATE:
        f->body.state.echoed_seq = (uint32_t)v[k++];
        for (i = 0; i < 6; ++i) f->body.state.pose[i] = (int32_t)v[k++];
        for (i = 0; i < 6; ++i) f->body.state.offset[i] = (int32_t)v[k++];
        f->body.state.status = (uint32_t)v[k++];
        f->body.state.error_code = (uint32_t)v[k++];
        f->body.state.time_us = (uint64_t)v[k++];
        break;
    case MPCL_FAULT:
        f->body.fault.code = (uint32_t)v[k++];
        f->body.fault.length = (uint16_t)v[k++];
        for (i = 0; i < f->body.fault.length; ++i) f->body.fault.text[i] = (uint8_t)v[k++];
        break;
    default:
        break;
    }
    return 0;
}

/* Reads `data` through a fresh reader fed `chunk` bytes at a time. Writes each frame as its value count
 * followed by its values; returns how many int64 were written (-1: out too small) and sets *error to
 * MPCL_OK or the error that ended the stream. */
int mpcl_test_stream(const uint8_t *data, size_t length, size_t chunk, int64_t *out, size_t capacity, int *error)
{
    static mpcl_reader reader;  /* 1 KB: static rather than on a small controller task's stack */
    mpcl_frame frame;
    size_t offset = 0, written = 0;
    int result = 0;
    mpcl_reader_init(&reader);
    *error = MPCL_OK;
    if (chunk == 0) chunk = 1;
    while (offset < length || result == 1) {
        if (offset < length) {
            size_t piece = length - offset < chunk ? length - offset : chunk;
            offset += mpcl_reader_feed(&reader, data + offset, piece);
        }
        while ((result = mpcl_reader_next(&reader, &frame)) == 1) {
            int n;
            if (capacity - written < 4 + 17 + MPCL_MAX_FAULT_TEXT) return -1;
            n = mpcl_flatten(&frame, out + written + 1, capacity - written - 1);
            out[written] = n;
            written += 1 + (size_t)n;
        }
        if (result < 0) {
            *error = result;
            break;
        }
    }
    return (int)written;
}

/* Encodes a flattened frame; the number of bytes, or a negative error. */
int mpcl_test_encode(const int64_t *values, size_t n, uint8_t *out, size_t capacity)
{
    mpcl_frame frame;
    if (mpcl_unflatten(values, n, &frame) != 0) return MPCL_E_TYPE;
    return mpcl_encode(&frame, out, capacity);
}

#ifndef MPCL_SELFTEST_NO_MAIN

static int failures = 0;

static void fail(int line, const char *what)
{
    fprintf(stderr, "vectors line %d: %s\n", line, what);
    ++failures;
}

static size_t parse_hex(const char *hex, uint8_t *out, size_t capacity)
{
    size_t n = 0;
    unsigned value;
    while (hex[0] && hex[1] && n < capacity && sscanf(hex, "%2x", &value) == 1) {
        out[n++] = (uint8_t)value;
        hex += 2;
    }
    return n;
}

static size_t parse_ints(char *text, int64_t *out, size_t capacity)
{
    size_t n = 0;
    char *token = strtok(text, " \t\r\n");
    while (token && n < capacity) {
        /* values up to 2^64 - 1 (a u64 time) parse unsigned and wrap as mpcl_flatten's do */
        out[n++] = token[0] == '-' ? (int64_t)strtoll(token, NULL, 10) : (int64_t)strtoull(token, NULL, 10);
        token = strtok(NULL, " \t\r\n");
    }
    return n;
}

int main(int argc, char **argv)
{
    static char line[MAX_LINE];
    static uint8_t stream[MAX_LINE / 2], encoded[4 + MPCL_MAX_FRAME];
    static int64_t got[3][MAX_VALUES], want[MAX_VALUES];
    static const size_t chunks[3] = {7, 1, MAX_LINE};
    int counts[3], errors[3], number = 0, streams = 0, frames = 0, rules = 0, k;
    size_t stream_length = 0, position = 0, frame_offset = 0;
    FILE *file = argc > 1 ? fopen(argv[1], "r") : NULL;
    if (!file) {
        fprintf(stderr, "usage: %s vectors.txt\n", argv[0]);
        return 2;
    }
    while (fgets(line, sizeof line, file)) {
        ++number;
        if (strncmp(line, "stream ", 7) == 0) {
            stream_length = parse_hex(line + 7, stream, sizeof stream);
            for (k = 0; k < 3; ++k)
                counts[k] = mpcl_test_stream(stream, stream_length, chunks[k], got[k], MAX_VALUES, &errors[k]);
            for (k = 1; k < 3; ++k)
                if (counts[k] != counts[0] || errors[k] != errors[0]
                    || memcmp(got[k], got[0], sizeof got[0][0] * (size_t)(counts[0] > 0 ? counts[0] : 0)) != 0)
                    fail(number, "the stream reads differently in other pieces");
            position = frame_offset = 0;
            ++streams;
        } else if (strncmp(line, "frame ", 6) == 0) {
            size_t n = parse_ints(line + 6, want, MAX_VALUES);
            int length;
            if ((int)position >= counts[0] || got[0][position] != (int64_t)n
                || memcmp(got[0] + position + 1, want, n * sizeof want[0]) != 0) {
                fail(number, "a frame decoded differently");
                position = (size_t)counts[0];
                continue;
            }
            position += 1 + n;
            length = mpcl_test_encode(want, n, encoded, sizeof encoded);
            if (length < 0 || frame_offset + (size_t)length > stream_length
                || memcmp(encoded, stream + frame_offset, (size_t)length) != 0)
                fail(number, "a frame re-encoded differently");
            frame_offset += length > 0 ? (size_t)length : 0;
            ++frames;
        } else if (strncmp(line, "end", 3) == 0 || strncmp(line, "error ", 6) == 0) {
            const char *rule = line[0] == 'e' && line[1] == 'n' ? "ok" : strtok(line + 6, " \t\r\n");
            if ((int)position != counts[0]) fail(number, "the stream yielded more frames");
            if (strcmp(mpcl_error_name(errors[0]), rule ? rule : "") != 0) {
                fprintf(stderr, "vectors line %d: ended with %s, expected %s\n", number,
                        mpcl_error_name(errors[0]), rule ? rule : "?");
                ++failures;
            }
        } else if (strncmp(line, "sequence ", 9) == 0) {
            char verdict[8];
            unsigned long last, seq;
            static const char *const names[3] = {"new", "old", "gap"};
            if (sscanf(line + 9, "%lu %lu %7s", &last, &seq, verdict) != 3
                || strcmp(names[mpcl_sequence_verdict((uint32_t)last, (uint32_t)seq)], verdict) != 0)
                fail(number, "sequence verdict differs");
            ++rules;
        } else if (strncmp(line, "clamp ", 6) == 0) {
            int32_t increment[6], limit[6];
            size_t n = parse_ints(line + 6, want, MAX_VALUES);
            int i, cut;
            if (n != 19) {
                fail(number, "a clamp line needs 19 values");
                continue;
            }
            for (i = 0; i < 6; ++i) {
                increment[i] = (int32_t)want[i];
                limit[i] = (int32_t)want[6 + i];
            }
            cut = mpcl_clamp(increment, limit);
            for (i = 0; i < 6; ++i)
                if (increment[i] != want[12 + i]) cut = -1;
            if (cut != want[18]) fail(number, "clamp differs");
            ++rules;
        } else if (line[0] != '#' && line[0] != '\n') {
            fail(number, "not a vector");
        }
    }
    fclose(file);
    printf("mpcl: %d streams, %d frames, %d rule checks; %d failure(s)\n", streams, frames, rules, failures);
    return failures == 0 && streams > 0 ? 0 : 1;
}

#endif
