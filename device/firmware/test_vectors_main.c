/*
 * test_vectors_main.c - host test program for the pen's frame encoder.
 *
 *   test_vectors VECTORS.txt   run every case of the shared vector file through the C encoder;
 *                              one line per failure ("line N: ..."), then "P passed, F failed";
 *                              exit 0 only if every case passed (an unknown kind or key fails)
 *   test_vectors --errors      the encoder's refusals (bad counts, small buffers, bad headers)
 *   test_vectors --encode      read cases in the vector syntax without the expected bytes
 *                              (and "pen-header") on stdin, write the frames to stdout
 *   test_vectors --info        print the encoder's constants and the pen's header frame (hex)
 *
 * Built by tests/test_firmware.py with the system C compiler. Every encoding is made into a
 * heap buffer of exactly the expected size (and once more into one byte less, which must be
 * refused), so a sanitizer build catches any write past the caller's capacity.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "tactile_frame.h"
#include "pen_info.h"

#define MAX_KEYS 16

typedef struct {
    const char *key;
    char *val;
} kv_t;

typedef struct {
    long line;
    const char *kind;
    kv_t kv[MAX_KEYS];
    int n;
} case_t;

static char g_msg[512]; /* why the current case failed */

static int fail(const char *fmt, const char *a, const char *b)
{
    snprintf(g_msg, sizeof g_msg, fmt, a ? a : "", b ? b : "");
    return 0;
}

/* --------------------------------------------------------------------------- line reading */

/* One line of any length into a growing buffer; returns 0 at end of file. */
static int read_line(FILE *f, char **buf, size_t *cap)
{
    size_t n = 0;
    int c;
    if (*buf == NULL) {
        *cap = 256;
        *buf = malloc(*cap);
        if (*buf == NULL) {
            return 0;
        }
    }
    while ((c = fgetc(f)) != EOF) {
        if (n + 1 >= *cap) {
            char *bigger = realloc(*buf, *cap * 2);
            if (bigger == NULL) {
                return 0;
            }
            *buf = bigger;
            *cap *= 2;
        }
        if (c == '\n') {
            break;
        }
        (*buf)[n++] = (char)c;
    }
    (*buf)[n] = '\0';
    return c != EOF || n > 0;
}

static int is_space(char c)
{
    return c == ' ' || c == '\t' || c == '\r' || c == '\n' || c == '\v' || c == '\f';
}

/* Split "kind key=value ..." in place. Returns 0 for a blank or comment line, 1 for a case,
 * -1 for a malformed one (g_msg says why). Same rules as vectors.parse_line. */
static int split_case(char *s, case_t *cs)
{
    char *tok[MAX_KEYS + 2];
    int ntok = 0, t, k;
    cs->n = 0;
    while (*s) { /* whitespace-separated tokens, terminated in place */
        while (is_space(*s)) {
            *s++ = '\0';
        }
        if (*s == '\0') {
            break;
        }
        if (ntok == MAX_KEYS + 1) {
            fail("too many fields", NULL, NULL);
            return -1;
        }
        tok[ntok++] = s;
        while (*s && !is_space(*s)) {
            s++;
        }
    }
    if (ntok == 0 || tok[0][0] == '#') {
        return 0;
    }
    cs->kind = tok[0];
    for (t = 1; t < ntok; t++) {
        char *eq = strchr(tok[t], '=');
        if (eq == NULL) {
            fail("field '%s' is not key=value", tok[t], NULL);
            return -1;
        }
        *eq = '\0';
        for (k = 0; k < cs->n; k++) {
            if (strcmp(cs->kv[k].key, tok[t]) == 0) {
                fail("duplicate key '%s'", tok[t], NULL);
                return -1;
            }
        }
        cs->kv[cs->n].key = tok[t];
        cs->kv[cs->n].val = eq + 1;
        cs->n++;
    }
    return 1;
}

static char *get(const case_t *cs, const char *key)
{
    int k;
    for (k = 0; k < cs->n; k++) {
        if (strcmp(cs->kv[k].key, key) == 0) {
            return cs->kv[k].val;
        }
    }
    return NULL;
}

/* Every key present is allowed and every required key is present (nothing silently
 * ignored). `keys` is a NULL-terminated list; `optional` is allowed but not required. */
static int check_keys(const case_t *cs, const char *const *keys, const char *optional,
                      int require_optional)
{
    int k, j, known;
    for (k = 0; k < cs->n; k++) {
        known = optional != NULL && strcmp(cs->kv[k].key, optional) == 0;
        for (j = 0; keys[j] != NULL && !known; j++) {
            known = strcmp(cs->kv[k].key, keys[j]) == 0;
        }
        if (!known) {
            return fail("unknown key '%s' for kind '%s'", cs->kv[k].key, cs->kind);
        }
    }
    for (j = 0; keys[j] != NULL; j++) {
        if (get(cs, keys[j]) == NULL) {
            return fail("missing key '%s' for kind '%s'", keys[j], cs->kind);
        }
    }
    if (optional != NULL && require_optional && get(cs, optional) == NULL) {
        return fail("missing key '%s' for kind '%s'", optional, cs->kind);
    }
    if (optional != NULL && !require_optional && get(cs, optional) != NULL) {
        return fail("key '%s' not expected here (kind '%s')", optional, cs->kind);
    }
    return 1;
}

/* ------------------------------------------------------------------------------ values */

static int hex_digit(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'a' && c <= 'f') {
        return c - 'a' + 10;
    }
    if (c >= 'A' && c <= 'F') {
        return c - 'A' + 10;
    }
    return -1;
}

/* Hex string ('-' = empty) into a new buffer (caller frees). */
static int parse_hex(const char *key, const char *s, uint8_t **out, size_t *len)
{
    size_t n, i;
    if (strcmp(s, "-") == 0) {
        s = "";
    }
    n = strlen(s);
    if (n % 2 != 0) {
        return fail("%s: odd number of hex digits", key, NULL);
    }
    *len = n / 2;
    *out = malloc(*len + 1);
    if (*out == NULL) {
        return fail("%s: out of memory", key, NULL);
    }
    for (i = 0; i < *len; i++) {
        int hi = hex_digit(s[2 * i]), lo = hex_digit(s[2 * i + 1]);
        if (hi < 0 || lo < 0) {
            free(*out);
            *out = NULL;
            return fail("%s: not hex: '%s'", key, s);
        }
        (*out)[i] = (uint8_t)(hi * 16 + lo);
    }
    return 1;
}

/* Integer in [lo, hi]: decimal, or hex with 0x. */
static int parse_int(const char *key, const char *s, long long lo, long long hi, long long *v)
{
    char *end;
    if (*s == '\0') {
        return fail("%s: empty number", key, NULL);
    }
    *v = strtoll(s, &end, 0);
    if (*end != '\0' || *v < lo || *v > hi) {
        return fail("%s: bad or out-of-range number '%s'", key, s);
    }
    return 1;
}

static int parse_u32(const char *key, const char *s, uint32_t *v)
{
    long long x;
    if (!parse_int(key, s, 0, 0xFFFFFFFFLL, &x)) {
        return 0;
    }
    *v = (uint32_t)x;
    return 1;
}

/* A float32 given as its bit pattern (0x3c23d70a). */
static int parse_f32_bits(const char *key, const char *s, float *f)
{
    uint32_t u;
    if (strncmp(s, "0x", 2) != 0 || strlen(s) != 10 || !parse_u32(key, s, &u)) {
        return fail("%s: float bits must be 0x + 8 hex digits, got '%s'", key, s);
    }
    memcpy(f, &u, sizeof *f);
    return 1;
}

static void to_hex(const uint8_t *b, size_t n, char *out)
{
    static const char digits[] = "0123456789abcdef";
    size_t i;
    for (i = 0; i < n; i++) {
        out[2 * i] = digits[b[i] >> 4];
        out[2 * i + 1] = digits[b[i] & 15];
    }
    out[2 * n] = '\0';
}

/* ------------------------------------------------------------------- encoding a case */

/* Inputs of one case, parsed; the encoders are called through encode(). */
typedef struct {
    enum { K_CRC, K_COBS, K_SAMPLES, K_HEADER, K_PEN_HEADER } kind;
    uint8_t *data;     /* crc, cobs */
    size_t data_len;
    uint32_t seq, t_us; /* samples */
    uint8_t channels, samples;
    int16_t *values;
    tf_header header; /* header */
    tf_channel chans[TF_MAX_CHANNELS];
} input_t;

static void free_input(input_t *in)
{
    free(in->data);
    free(in->values);
    in->data = NULL;
    in->values = NULL;
}

static size_t encode(const input_t *in, uint8_t *out, size_t cap)
{
    switch (in->kind) {
    case K_COBS:
        return tf_cobs_encode(in->data, in->data_len, out, cap);
    case K_SAMPLES:
        return tf_encode_samples(in->seq, in->t_us, in->channels, in->samples, in->values, out,
                                 cap);
    case K_HEADER:
        return tf_encode_header(&in->header, out, cap);
    case K_PEN_HEADER:
        return tf_encode_header(&TP_HEADER, out, cap);
    default:
        return 0;
    }
}

static int parse_samples(const case_t *cs, input_t *in)
{
    long long c, n, v;
    size_t count, i = 0;
    char *p, *next;
    if (!parse_u32("seq", get(cs, "seq"), &in->seq) ||
        !parse_u32("t_us", get(cs, "t_us"), &in->t_us) ||
        !parse_int("channels", get(cs, "channels"), 0, 255, &c) ||
        !parse_int("samples", get(cs, "samples"), 0, 255, &n)) {
        return 0;
    }
    in->channels = (uint8_t)c;
    in->samples = (uint8_t)n;
    count = (size_t)(c * n);
    in->values = malloc((count ? count : 1) * sizeof *in->values);
    if (in->values == NULL) {
        return fail("data: out of memory", NULL, NULL);
    }
    for (p = get(cs, "data"); p != NULL; p = next) {
        next = strchr(p, ',');
        if (next != NULL) {
            *next++ = '\0';
        }
        if (i == count) {
            return fail("data: more values than channels x samples", NULL, NULL);
        }
        if (!parse_int("data", p, -32768, 32767, &v)) {
            return 0;
        }
        in->values[i++] = (int16_t)v;
    }
    if (i != count) {
        return fail("data: fewer values than channels x samples", NULL, NULL);
    }
    return 1;
}

static int parse_header(const case_t *cs, input_t *in)
{
    long long version;
    char *p, *next;
    int c = 0;
    if (!parse_int("version", get(cs, "version"), 0, 255, &version) ||
        !parse_f32_bits("rate_bits", get(cs, "rate_bits"), &in->header.rate_hz)) {
        return 0;
    }
    in->header.version = (uint8_t)version;
    in->header.device = get(cs, "device");
    for (p = get(cs, "channels"); p != NULL; p = next) {
        char *f[4];
        int k;
        next = strchr(p, ',');
        if (next != NULL) {
            *next++ = '\0';
        }
        if (c == (int)TF_MAX_CHANNELS) {
            return fail("channels: more than the encoder's maximum", NULL, NULL);
        }
        f[0] = p;
        for (k = 1; k < 4; k++) {
            f[k] = strchr(f[k - 1], ':');
            if (f[k] == NULL) {
                return fail("channels: '%s' is not NAME:UNIT:SCALEBITS:OFFSETBITS", p, NULL);
            }
            *f[k]++ = '\0';
        }
        in->chans[c].name = f[0];
        in->chans[c].unit = f[1];
        if (!parse_f32_bits("scale", f[2], &in->chans[c].scale) ||
            !parse_f32_bits("offset", f[3], &in->chans[c].offset)) {
            return 0;
        }
        c++;
    }
    in->header.n_channels = (uint8_t)c;
    in->header.channels = in->chans;
    return 1;
}

static const char *const CRC_KEYS[] = {"data", "crc", NULL};
static const char *const COBS_KEYS[] = {"data", "encoded", NULL};
static const char *const SAMPLES_KEYS[] = {"seq", "t_us", "channels", "samples", "data", NULL};
static const char *const HEADER_KEYS[] = {"version", "rate_bits", "device", "channels", NULL};
static const char *const NO_KEYS[] = {NULL};

/* Parse a case's inputs. `with_expected`: the expected-bytes key must be present (vector
 * file) or absent (--encode). */
static int parse_input(const case_t *cs, input_t *in, int with_expected)
{
    memset(in, 0, sizeof *in);
    if (strcmp(cs->kind, "crc") == 0) {
        in->kind = K_CRC;
        return check_keys(cs, CRC_KEYS, NULL, 0) &&
               parse_hex("data", get(cs, "data"), &in->data, &in->data_len);
    }
    if (strcmp(cs->kind, "cobs") == 0) {
        in->kind = K_COBS;
        return check_keys(cs, COBS_KEYS, NULL, 0) &&
               parse_hex("data", get(cs, "data"), &in->data, &in->data_len);
    }
    if (strcmp(cs->kind, "samples") == 0) {
        in->kind = K_SAMPLES;
        return check_keys(cs, SAMPLES_KEYS, "frame", with_expected) && parse_samples(cs, in);
    }
    if (strcmp(cs->kind, "header") == 0) {
        in->kind = K_HEADER;
        return check_keys(cs, HEADER_KEYS, "frame", with_expected) && parse_header(cs, in);
    }
    if (strcmp(cs->kind, "pen-header") == 0 && !with_expected) {
        in->kind = K_PEN_HEADER;
        return check_keys(cs, NO_KEYS, NULL, 0);
    }
    return fail("unknown kind '%s'", cs->kind, NULL);
}

/* Encode into a buffer of exactly the expected size (must give the expected bytes), then
 * into one byte less (must be refused). */
static int check_bytes(const input_t *in, const uint8_t *want, size_t want_len)
{
    uint8_t *out = malloc(want_len ? want_len : 1);
    size_t got;
    int ok = 1;
    if (out == NULL) {
        return fail("out of memory", NULL, NULL);
    }
    got = encode(in, out, want_len);
    if (got != want_len || memcmp(out, want, want_len) != 0) {
        char *a = malloc(2 * (got < want_len ? want_len : got) + 1);
        char *b = malloc(2 * want_len + 1);
        if (a != NULL && b != NULL) {
            to_hex(out, got < want_len ? got : want_len, a);
            to_hex(want, want_len, b);
            ok = fail("got %s, expected %s", got ? a : "(refused)", b);
        } else {
            ok = fail("bytes differ", NULL, NULL);
        }
        free(a);
        free(b);
    }
    free(out);
    if (ok && want_len > 0) {
        out = malloc(want_len - 1 ? want_len - 1 : 1);
        if (out == NULL) {
            return fail("out of memory", NULL, NULL);
        }
        if (encode(in, want_len - 1 ? out : NULL, want_len - 1) != 0) {
            ok = fail("not refused with a buffer one byte too small", NULL, NULL);
        }
        free(out);
    }
    return ok;
}

static int run_case(const case_t *cs)
{
    input_t in;
    uint8_t *want = NULL;
    size_t want_len = 0;
    int ok = parse_input(cs, &in, 1);
    if (ok && in.kind == K_CRC) {
        const char *want_s = get(cs, "crc");
        uint16_t got = tf_crc16(in.data, in.data_len);
        size_t half = in.data_len / 2;
        uint16_t chained = tf_crc16_update(tf_crc16(in.data, half), in.data + half,
                                           in.data_len - half);
        char got_s[8];
        snprintf(got_s, sizeof got_s, "%04x", got);
        /* the file writes the CRC as exactly 4 lower-case hex digits */
        if (strcmp(got_s, want_s) != 0) {
            ok = fail("crc: got %s, expected %s", got_s, want_s);
        } else if (chained != got) {
            ok = fail("crc: tf_crc16_update over two halves differs from tf_crc16", NULL, NULL);
        }
    } else if (ok) {
        const char *key = in.kind == K_COBS ? "encoded" : "frame";
        ok = parse_hex(key, get(cs, key), &want, &want_len) && check_bytes(&in, want, want_len);
    }
    free(want);
    free_input(&in);
    return ok;
}

static int run_vectors(const char *path)
{
    FILE *f = fopen(path, "r");
    char *line = NULL;
    size_t cap = 0;
    long lineno = 0, passed = 0, failed = 0;
    if (f == NULL) {
        fprintf(stderr, "cannot open %s\n", path);
        return 2;
    }
    while (read_line(f, &line, &cap)) {
        case_t cs;
        int r;
        lineno++;
        g_msg[0] = '\0';
        r = split_case(line, &cs);
        if (r == 0) {
            continue;
        }
        cs.line = lineno;
        if (r > 0 && run_case(&cs)) {
            passed++;
        } else {
            failed++;
            printf("line %ld: %s: %s\n", lineno, r > 0 ? cs.kind : "?", g_msg);
        }
    }
    free(line);
    fclose(f);
    printf("%ld passed, %ld failed\n", passed, failed);
    return (failed == 0 && passed > 0) ? 0 : 1;
}

/* ------------------------------------------------------------------------- --encode */

static int run_encode(void)
{
    char *line = NULL;
    size_t cap = 0;
    long lineno = 0;
    static uint8_t out[TF_MAX_FRAME];
    while (read_line(stdin, &line, &cap)) {
        case_t cs;
        input_t in;
        size_t n = 0;
        int r, ok;
        lineno++;
        r = split_case(line, &cs);
        if (r == 0) {
            continue;
        }
        ok = r > 0 && parse_input(&cs, &in, 0);
        if (ok && in.kind != K_CRC && in.kind != K_COBS) {
            n = encode(&in, out, sizeof out);
        }
        if (r > 0) {
            free_input(&in);
        }
        if (!ok || n == 0) {
            fprintf(stderr, "stdin line %ld: %s\n", lineno, ok ? "encoder refused" : g_msg);
            free(line);
            return 1;
        }
        fwrite(out, 1, n, stdout);
    }
    free(line);
    return fflush(stdout) == 0 ? 0 : 1;
}

/* ------------------------------------------------------------------------- --errors */

static long g_pass, g_fail;

static void expect(int cond, const char *what)
{
    if (cond) {
        g_pass++;
    } else {
        g_fail++;
        printf("FAIL: %s\n", what);
    }
}

static size_t header1(const char *name, const char *unit, float scale, float offset,
                      float rate, const char *device, uint8_t *out, size_t cap)
{
    tf_channel ch;
    tf_header h;
    ch.name = name;
    ch.unit = unit;
    ch.scale = scale;
    ch.offset = offset;
    h.version = TF_PROTOCOL_VERSION;
    h.rate_hz = rate;
    h.device = device;
    h.n_channels = 1;
    h.channels = &ch;
    return tf_encode_header(&h, out, cap);
}

static float f32_from_bits(uint32_t u)
{
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

static int run_errors(void)
{
    static uint8_t out[TF_MAX_FRAME];
    static int16_t data[TF_MAX_CHANNELS * TF_MAX_SAMPLES];
    static tf_channel many[TF_MAX_CHANNELS + 1];
    static char names[TF_MAX_CHANNELS + 1][TF_MAX_NAME + 1];
    static const char n32[] = "abcdefghijklmnopqrstuvwxyz012345";  /* 32 bytes */
    static const char n33[] = "abcdefghijklmnopqrstuvwxyz0123456"; /* 33 bytes */
    const float nan = f32_from_bits(0x7FC00000u), inf = f32_from_bits(0x7F800000u);
    const size_t cap = sizeof out;
    tf_header h;
    size_t n;
    int i;

    expect(tf_crc16((const uint8_t *)"123456789", 9) == 0x29B1, "crc check value 0x29B1");
    expect(tf_cobs_encode(NULL, 0, out, cap) == 1 && out[0] == 1, "cobs of nothing is 01");
    expect(tf_cobs_encode(NULL, 3, out, cap) == 0, "cobs refuses NULL input");
    expect(tf_cobs_encode((const uint8_t *)"a", 1, NULL, 0) == 0, "cobs refuses no buffer");

    expect(tf_encode_samples(0, 0, 8, 1, data, out, cap) == 31, "8 x 1 samples frame is 31 B");
    expect(tf_encode_samples(0, 0, 8, 1, NULL, out, cap) == 0, "samples refuse NULL data");
    expect(tf_encode_samples(0, 0, 0, 1, data, out, cap) == 0, "samples refuse 0 channels");
    expect(tf_encode_samples(0, 0, 33, 1, data, out, cap) == 0, "samples refuse 33 channels");
    expect(tf_encode_samples(0, 0, 8, 0, data, out, cap) == 0, "samples refuse 0 samples");
    expect(tf_encode_samples(0, 0, 8, 33, data, out, cap) == 0, "samples refuse 33 samples");
    expect(tf_encode_samples(0, 0, 32, 32, data, out, cap) != 0, "32 x 32 fits (2059 B body)");
    expect(tf_encode_samples(0, 0, 8, 1, data, out, 30) == 0, "samples refuse a short buffer");
    expect(tf_encode_samples(0, 0, 8, 1, data, NULL, 100) == 0, "samples refuse no buffer");
    expect(TF_SAMPLES_FRAME_SIZE(8, 1) == 31, "TF_SAMPLES_FRAME_SIZE(8, 1) == 31");
    for (i = 0; i < (int)(TF_MAX_CHANNELS * TF_MAX_SAMPLES); i++) {
        data[i] = (int16_t)(i * 7919);
    }
    n = tf_encode_samples(1, 2, 32, 32, data, out, cap);
    expect(n != 0 && n <= TF_SAMPLES_FRAME_SIZE(32, 32), "TF_SAMPLES_FRAME_SIZE is a bound");

    expect(header1("a", "V", 1.0f, 0.0f, 100.0f, "x", out, cap) != 0, "minimal header");
    expect(header1("a", "", 1.0f, 0.0f, 100.0f, "", out, cap) != 0, "empty unit and device");
    expect(header1(n32, n32, 1.0f, 0.0f, 100.0f, n32, out, cap) != 0, "32-byte strings");
    expect(header1("a", "\xc2\xb5V", 1.0f, 0.0f, 1e6f, "pen \xe2\x9c\x8e", out, cap) != 0,
           "UTF-8 strings, rate 1e6");
    expect(header1("", "V", 1.0f, 0.0f, 100.0f, "x", out, cap) == 0, "empty name refused");
    expect(header1(NULL, "V", 1.0f, 0.0f, 100.0f, "x", out, cap) == 0, "NULL name refused");
    expect(header1("a", NULL, 1.0f, 0.0f, 100.0f, "x", out, cap) == 0, "NULL unit refused");
    expect(header1("a", "V", 1.0f, 0.0f, 100.0f, NULL, out, cap) == 0, "NULL device refused");
    expect(header1(n33, "V", 1.0f, 0.0f, 100.0f, "x", out, cap) == 0, "33-byte name refused");
    expect(header1("a", n33, 1.0f, 0.0f, 100.0f, "x", out, cap) == 0, "33-byte unit refused");
    expect(header1("a", "V", 1.0f, 0.0f, 100.0f, n33, out, cap) == 0, "33-byte device refused");
    expect(header1("\xc0\x80", "V", 1.0f, 0.0f, 100.0f, "x", out, cap) == 0, "overlong UTF-8");
    expect(header1("a", "\xed\xa0\x80", 1.0f, 0.0f, 100.0f, "x", out, cap) == 0, "surrogate");
    expect(header1("a", "V", 1.0f, 0.0f, 100.0f, "\x80", out, cap) == 0, "stray continuation");
    expect(header1("a", "\xe2\x82", 1.0f, 0.0f, 100.0f, "x", out, cap) == 0, "truncated UTF-8");
    expect(header1("a", "V", 0.0f, 0.0f, 100.0f, "x", out, cap) == 0, "zero scale refused");
    expect(header1("a", "V", -0.0f, 0.0f, 100.0f, "x", out, cap) == 0, "-0 scale refused");
    expect(header1("a", "V", nan, 0.0f, 100.0f, "x", out, cap) == 0, "NaN scale refused");
    expect(header1("a", "V", inf, 0.0f, 100.0f, "x", out, cap) == 0, "inf scale refused");
    expect(header1("a", "V", 1.0f, -inf, 100.0f, "x", out, cap) == 0, "inf offset refused");
    expect(header1("a", "V", 1.0f, 0.0f, 0.0f, "x", out, cap) == 0, "zero rate refused");
    expect(header1("a", "V", 1.0f, 0.0f, -1.0f, "x", out, cap) == 0, "negative rate refused");
    expect(header1("a", "V", 1.0f, 0.0f, nan, "x", out, cap) == 0, "NaN rate refused");
    expect(header1("a", "V", 1.0f, 0.0f, 1.5e6f, "x", out, cap) == 0, "rate > 1e6 refused");
    expect(tf_encode_header(NULL, out, cap) == 0, "NULL header refused");

    h = TP_HEADER;
    n = tf_encode_header(&h, out, cap);
    expect(n != 0 && tf_encode_header(&h, out, n - 1) == 0, "pen header: short buffer refused");
    h.n_channels = 0;
    expect(tf_encode_header(&h, out, cap) == 0, "0 channels refused");
    for (i = 0; i <= (int)TF_MAX_CHANNELS; i++) {
        snprintf(names[i], sizeof names[i], "c%d", i);
        many[i].name = names[i];
        many[i].unit = "u";
        many[i].scale = 1.0f;
        many[i].offset = 0.0f;
    }
    h.channels = many;
    h.n_channels = TF_MAX_CHANNELS;
    expect(tf_encode_header(&h, out, cap) != 0, "32 channels");
    h.n_channels = TF_MAX_CHANNELS + 1;
    expect(tf_encode_header(&h, out, cap) == 0, "33 channels refused");
    h.n_channels = 3;
    many[2].name = "c0";
    expect(tf_encode_header(&h, out, cap) == 0, "duplicate channel names refused");
    for (i = 0; i < (int)TF_MAX_CHANNELS; i++) { /* 32-byte unique names and units */
        memcpy(names[i], n32, sizeof n32);
        names[i][0] = (char)('A' + i);
        many[i].name = names[i];
        many[i].unit = n32;
    }
    /* the largest header: 8 fixed + 33 device + 32 x 74 = 2409 B */
    h.device = n32;
    h.n_channels = TF_MAX_CHANNELS;
    n = tf_encode_header(&h, out, cap);
    expect(n != 0 && n <= TF_MAX_FRAME, "largest header (2409 B body) fits TF_MAX_FRAME");

    printf("%ld passed, %ld failed\n", g_pass, g_fail);
    return g_fail == 0 ? 0 : 1;
}

/* ---------------------------------------------------------------------------- --info */

static int run_info(void)
{
    static uint8_t out[TF_MAX_FRAME];
    static char hex[2 * TF_MAX_FRAME + 1];
    size_t n = tf_encode_header(&TP_HEADER, out, sizeof out);
    to_hex(out, n, hex);
    printf("max_frame %u\n", (unsigned)TF_MAX_FRAME);
    printf("max_body %u\n", (unsigned)TF_MAX_BODY);
    printf("pen_header %s\n", n ? hex : "-");
    return n ? 0 : 1;
}

int main(int argc, char **argv)
{
    if (argc == 2 && strcmp(argv[1], "--encode") == 0) {
        return run_encode();
    }
    if (argc == 2 && strcmp(argv[1], "--errors") == 0) {
        return run_errors();
    }
    if (argc == 2 && strcmp(argv[1], "--info") == 0) {
        return run_info();
    }
    if (argc == 2 && argv[1][0] != '-') {
        return run_vectors(argv[1]);
    }
    fprintf(stderr, "usage: %s VECTORS.txt | --encode | --errors | --info\n", argv[0]);
    return 2;
}
