/*
 * tactile_frame.c - the pen's wire-frame encoder (portable C99). See tactile_frame.h.
 *
 * The frame is built in a single pass: each body byte goes through the CRC and straight into
 * the COBS stuffer, which writes into the caller's buffer. No intermediate copy of the body
 * is needed, so the only memory is the output buffer and a few words of stack.
 */
#include "tactile_frame.h"

#include <string.h>

/* The header carries floats as IEEE-754 binary32 bit patterns. */
typedef char tf_float_must_be_32_bits[(sizeof(float) == 4) ? 1 : -1];

uint16_t tf_crc16_update(uint16_t crc, const uint8_t *data, size_t len)
{
    size_t i;
    int bit;
    for (i = 0; i < len; i++) {
        crc = (uint16_t)(crc ^ ((uint16_t)data[i] << 8));
        for (bit = 0; bit < 8; bit++) {
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

uint16_t tf_crc16(const uint8_t *data, size_t len)
{
    return tf_crc16_update(0xFFFFu, data, len);
}

/* ------------------------------------------------------------------------------------------
 * Streaming COBS writer.
 *
 * A block is a code byte (its length + 1) followed by up to 254 non-zero bytes. The code
 * byte's slot is reserved when the block opens and filled in when it closes. A full block
 * (code 0xFF) carries no implied zero and closes at once; the next block opens lazily, on the
 * next byte, so that a full block ending the data is not followed by an empty block (the
 * classic encoder, byte-identical to protocol.cobs_encode).
 */
typedef struct {
    uint8_t *out;
    size_t cap;
    size_t len;      /* bytes written so far, reserved code slots included */
    size_t code_pos; /* slot of the open block's code byte */
    uint8_t code;    /* open block's length + 1 */
    uint8_t open;    /* a block is open */
    uint8_t err;     /* ran out of room */
    uint16_t crc;    /* CRC of the body bytes so far */
} tf_writer;

static void w_open_block(tf_writer *w)
{
    if (w->len >= w->cap) {
        w->err = 1;
        return;
    }
    w->code_pos = w->len++;
    w->code = 1;
    w->open = 1;
}

static void w_init(tf_writer *w, uint8_t *out, size_t cap)
{
    w->out = out;
    w->cap = (out == NULL) ? 0 : cap;
    w->len = 0;
    w->code_pos = 0;
    w->code = 1;
    w->open = 0;
    w->err = 0;
    w->crc = 0xFFFFu;
    w_open_block(w); /* even empty data encodes to one block (0x01) */
}

/* Stuff one byte (no CRC). */
static void w_stuff(tf_writer *w, uint8_t b)
{
    if (w->err) {
        return;
    }
    if (!w->open) {
        w_open_block(w);
        if (w->err) {
            return;
        }
    }
    if (b == 0) {
        w->out[w->code_pos] = w->code; /* the zero is implied by ending the block here */
        w_open_block(w);
        return;
    }
    if (w->len >= w->cap) {
        w->err = 1;
        return;
    }
    w->out[w->len++] = b;
    w->code++;
    if (w->code == 0xFF) {
        w->out[w->code_pos] = 0xFF; /* full block: no implied zero */
        w->open = 0;
    }
}

/* Close the last block; append the delimiter if asked. Returns the length or 0. */
static size_t w_finish(tf_writer *w, int delimiter)
{
    if (w->err) {
        return 0;
    }
    if (w->open) {
        w->out[w->code_pos] = w->code;
        w->open = 0;
    }
    if (delimiter) {
        if (w->len >= w->cap) {
            return 0;
        }
        w->out[w->len++] = 0x00;
    }
    return w->len;
}

/* Body bytes: through the CRC, then stuffed. */
static void w_u8(tf_writer *w, uint8_t b)
{
    w->crc = tf_crc16_update(w->crc, &b, 1);
    w_stuff(w, b);
}

static void w_u16(tf_writer *w, uint16_t v)
{
    w_u8(w, (uint8_t)(v & 0xFFu));
    w_u8(w, (uint8_t)(v >> 8));
}

static void w_u32(tf_writer *w, uint32_t v)
{
    w_u8(w, (uint8_t)(v & 0xFFu));
    w_u8(w, (uint8_t)((v >> 8) & 0xFFu));
    w_u8(w, (uint8_t)((v >> 16) & 0xFFu));
    w_u8(w, (uint8_t)(v >> 24));
}

static uint32_t f32_bits(float f)
{
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return u;
}

/* A length-prefixed string; its length was checked by the caller. */
static void w_text(tf_writer *w, const char *s, size_t n)
{
    size_t i;
    w_u8(w, (uint8_t)n);
    for (i = 0; i < n; i++) {
        w_u8(w, (uint8_t)s[i]);
    }
}

/* Append the CRC (little-endian), close, delimit. */
static size_t w_frame_end(tf_writer *w)
{
    uint16_t crc = w->crc;
    w_stuff(w, (uint8_t)(crc & 0xFFu));
    w_stuff(w, (uint8_t)(crc >> 8));
    return w_finish(w, 1);
}

size_t tf_cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t cap)
{
    tf_writer w;
    size_t i;
    if (in == NULL && len != 0) {
        return 0;
    }
    w_init(&w, out, cap);
    for (i = 0; i < len && !w.err; i++) {
        w_stuff(&w, in[i]);
    }
    return w_finish(&w, 0);
}

size_t tf_encode_samples(uint32_t seq, uint32_t t_us, uint8_t n_channels, uint8_t n_samples,
                         const int16_t *data, uint8_t *out, size_t cap)
{
    tf_writer w;
    size_t i, count;
    if (data == NULL || n_channels < 1 || n_channels > TF_MAX_CHANNELS || n_samples < 1 ||
        n_samples > TF_MAX_SAMPLES) {
        return 0;
    }
    count = (size_t)n_channels * n_samples;
    if (TF_SAMPLES_HEAD + 2u * count > TF_MAX_BODY) {
        return 0;
    }
    w_init(&w, out, cap);
    w_u8(&w, TF_TYPE_SAMPLES);
    w_u32(&w, seq);
    w_u32(&w, t_us);
    w_u8(&w, n_channels);
    w_u8(&w, n_samples);
    for (i = 0; i < count && !w.err; i++) {
        w_u16(&w, (uint16_t)data[i]); /* two's complement bit pattern, low byte first */
    }
    return w_frame_end(&w);
}

/* ------------------------------------------------------------------------------------------
 * Header validation: refuse what the host would refuse (info.DeviceInfo / ChannelSpec), so
 * the pen never sends a header the decoder has to throw away.
 */

/* Length of `s` if it is at most `max` bytes, else max + 1 (never reads past s[max]). */
static size_t bounded_len(const char *s, size_t max)
{
    size_t n = 0;
    while (n <= max && s[n] != '\0') {
        n++;
    }
    return n;
}

/* Strict UTF-8 (no overlong forms, no surrogates, <= U+10FFFF), as Python decodes it. */
static int valid_utf8(const char *text, size_t n)
{
    const uint8_t *s = (const uint8_t *)text;
    size_t i = 0, k, more;
    while (i < n) {
        uint8_t c = s[i];
        uint8_t lo = 0x80, hi = 0xBF; /* range of the first continuation byte */
        if (c < 0x80) {
            i++;
            continue;
        } else if (c >= 0xC2 && c <= 0xDF) {
            more = 1;
        } else if (c >= 0xE0 && c <= 0xEF) {
            more = 2;
            if (c == 0xE0) {
                lo = 0xA0;
            } else if (c == 0xED) {
                hi = 0x9F;
            }
        } else if (c >= 0xF0 && c <= 0xF4) {
            more = 3;
            if (c == 0xF0) {
                lo = 0x90;
            } else if (c == 0xF4) {
                hi = 0x8F;
            }
        } else {
            return 0;
        }
        if (n - i - 1 < more) {
            return 0;
        }
        for (k = 1; k <= more; k++) {
            uint8_t b = s[i + k];
            if (k == 1 ? (b < lo || b > hi) : (b < 0x80 || b > 0xBF)) {
                return 0;
            }
        }
        i += more + 1;
    }
    return 1;
}

static int finite_bits(uint32_t u)
{
    return ((u >> 23) & 0xFFu) != 0xFFu;
}

/* A string field: non-NULL, valid UTF-8, at most TF_MAX_NAME bytes. Returns its length or
 * TF_MAX_NAME + 1 if invalid. */
static size_t text_len(const char *s)
{
    size_t n;
    if (s == NULL) {
        return TF_MAX_NAME + 1u;
    }
    n = bounded_len(s, TF_MAX_NAME);
    if (n > TF_MAX_NAME || !valid_utf8(s, n)) {
        return TF_MAX_NAME + 1u;
    }
    return n;
}

static int header_ok(const tf_header *h)
{
    uint32_t rate;
    size_t i, j;
    if (h == NULL || h->channels == NULL || h->n_channels < 1 ||
        h->n_channels > TF_MAX_CHANNELS || text_len(h->device) > TF_MAX_NAME) {
        return 0;
    }
    rate = f32_bits(h->rate_hz);
    if (!finite_bits(rate) || !(h->rate_hz > 0.0f && h->rate_hz <= 1.0e6f)) {
        return 0;
    }
    for (i = 0; i < h->n_channels; i++) {
        const tf_channel *c = &h->channels[i];
        uint32_t scale = f32_bits(c->scale), offset = f32_bits(c->offset);
        size_t name_len = text_len(c->name);
        if (name_len == 0 || name_len > TF_MAX_NAME || text_len(c->unit) > TF_MAX_NAME) {
            return 0;
        }
        if (!finite_bits(scale) || (scale & 0x7FFFFFFFu) == 0 || !finite_bits(offset)) {
            return 0;
        }
        for (j = 0; j < i; j++) {
            if (strcmp(h->channels[j].name, c->name) == 0) {
                return 0; /* duplicate channel name */
            }
        }
    }
    return 1;
}

size_t tf_encode_header(const tf_header *h, uint8_t *out, size_t cap)
{
    tf_writer w;
    size_t i, body;
    if (!header_ok(h)) {
        return 0;
    }
    /* type, version, f32 rate, n_channels, format, then the strings and per-channel floats */
    body = 8u + 1u + text_len(h->device);
    for (i = 0; i < h->n_channels; i++) {
        body += 1u + text_len(h->channels[i].name) + 1u + text_len(h->channels[i].unit) + 8u;
    }
    if (body > TF_MAX_BODY) {
        return 0;
    }
    w_init(&w, out, cap);
    w_u8(&w, TF_TYPE_HEADER);
    w_u8(&w, h->version);
    w_u32(&w, f32_bits(h->rate_hz));
    w_u8(&w, h->n_channels);
    w_u8(&w, TF_SAMPLE_FORMAT_INT16);
    w_text(&w, h->device, text_len(h->device));
    for (i = 0; i < h->n_channels && !w.err; i++) {
        const tf_channel *c = &h->channels[i];
        w_text(&w, c->name, text_len(c->name));
        w_text(&w, c->unit, text_len(c->unit));
        w_u32(&w, f32_bits(c->scale));
        w_u32(&w, f32_bits(c->offset));
    }
    return w_frame_end(&w);
}
