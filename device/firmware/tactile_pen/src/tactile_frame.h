/*
 * tactile_frame.h - the pen's wire-frame encoder (portable C99).
 *
 * A frame on the wire is COBS(body + crc16_le(body)) followed by one 0x00 delimiter
 * (device/PROTOCOL.md; device/protocol/codec.py is the reference implementation and
 * device/firmware/test_vectors.txt the byte-exact vectors both sides pass).
 *
 * - No heap, no libc beyond <stdint.h>/<stddef.h>/<string.h>; all buffers are the caller's.
 * - Every multi-byte field is written byte by byte, little-endian, so the output is the same
 *   on any host endianness. Floats are written as their IEEE-754 binary32 bit pattern.
 * - Every encoder returns the number of bytes written (delimiter included) or 0 on error:
 *   the buffer is too small, a count is out of range, a pointer is NULL, or a field the
 *   host would refuse (empty or over-long name, non-finite scale, ...). On error the
 *   contents of `out` are unspecified.
 * - Reentrant: no static state. Safe to call from any context (but keep it out of ISRs:
 *   a frame takes a few microseconds to tens of microseconds to encode).
 */
#ifndef TACTILE_FRAME_H
#define TACTILE_FRAME_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Limits: identical to device/protocol/codec.py and device/protocol/info.py. */
#define TF_PROTOCOL_VERSION 1u
#define TF_TYPE_HEADER 0x01u
#define TF_TYPE_SAMPLES 0x02u
#define TF_SAMPLE_FORMAT_INT16 1u
#define TF_MAX_CHANNELS 32u
#define TF_MAX_SAMPLES 32u  /* samples per frame */
#define TF_MAX_NAME 32u     /* bytes in a device string, channel name or unit */
/* Largest frame body (type byte .. last data byte, CRC excluded). Every frame within the
 * other limits fits: the largest header is 2409 bytes, the largest samples frame 2059. */
#define TF_MAX_BODY 2560u
#define TF_SAMPLES_HEAD 11u /* type, u32 seq, u32 t_us, u8 n_channels, u8 n_samples */

/* Encoded size of a body of `body` bytes: + 2 CRC bytes, + COBS overhead (at most one code
 * byte per 254 bytes, plus one), + 1 delimiter. An upper bound, exact when the stuffed data
 * holds no zero byte. */
#define TF_FRAME_SIZE(body) ((body) + 2u + ((body) + 2u) / 254u + 1u + 1u)

/* Buffer size that holds any samples frame of `c` channels x `n` samples. */
#define TF_SAMPLES_FRAME_SIZE(c, n) TF_FRAME_SIZE(TF_SAMPLES_HEAD + 2u * (c) * (n))

/* Buffer size that holds any frame at all (2574 bytes, delimiter included). */
#define TF_MAX_FRAME TF_FRAME_SIZE(TF_MAX_BODY)

typedef struct {
    const char *name; /* NUL-terminated UTF-8, 1..TF_MAX_NAME bytes, unique in the header */
    const char *unit; /* NUL-terminated UTF-8, 0..TF_MAX_NAME bytes */
    float scale;      /* value_in_unit = raw * scale + offset; finite, non-zero */
    float offset;     /* finite */
} tf_channel;

typedef struct {
    uint8_t version;            /* protocol version, TF_PROTOCOL_VERSION */
    float rate_hz;              /* sample rate, in (0, 1e6] */
    const char *device;         /* NUL-terminated UTF-8, 0..TF_MAX_NAME bytes */
    uint8_t n_channels;         /* 1..TF_MAX_CHANNELS */
    const tf_channel *channels; /* n_channels entries, in sample order */
} tf_header;

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0).
 * tf_crc16((const uint8_t *)"123456789", 9) == 0x29B1. */
uint16_t tf_crc16(const uint8_t *data, size_t len);

/* Continue a CRC over more bytes: tf_crc16(a + b) == tf_crc16_update(tf_crc16(a), b). */
uint16_t tf_crc16_update(uint16_t crc, const uint8_t *data, size_t len);

/* COBS-stuff `len` bytes of `in` into `out` (no delimiter appended). The result contains no
 * zero byte and is byte-identical to protocol.cobs_encode. Returns the encoded length (>= 1),
 * or 0 if it does not fit in `cap` bytes. `in` may be NULL only when len == 0; `in` and
 * `out` must not overlap. */
size_t tf_cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t cap);

/* A complete samples frame (type 0x02), delimiter included.
 *   seq: number of the first sample (the device's sample counter, wraps at 2^32)
 *   t_us: device clock at the first sample, microseconds (wraps at 2^32)
 *   data: n_samples x n_channels int16 values, sample-major: data[s * n_channels + c]
 * Requires 1 <= n_channels <= 32 and 1 <= n_samples <= 32. */
size_t tf_encode_samples(uint32_t seq, uint32_t t_us, uint8_t n_channels, uint8_t n_samples,
                         const int16_t *data, uint8_t *out, size_t cap);

/* A complete header frame (type 0x01), delimiter included. */
size_t tf_encode_header(const tf_header *h, uint8_t *out, size_t cap);

#ifdef __cplusplus
}
#endif

#endif /* TACTILE_FRAME_H */
