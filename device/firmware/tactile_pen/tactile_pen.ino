/*
 * tactile_pen.ino - firmware of the tactile pen.
 *
 * Board: Seeed Studio XIAO nRF52840 Sense, built with the "Seeed nRF52 Boards" package (the
 * Adafruit-based core, not the mbed one). IMU: the on-board LSM6DS3TR-C on the internal I2C
 * bus (Wire1). Tip sensor: pressure-conductive rubber in a voltage divider on A0.
 * See README.md beside this folder for wiring, building and flashing.
 *
 * Every 10 ms (100 Hz) a hardware timer interrupt counts a tick; loop() sees the new tick,
 * reads the tip ADC and the IMU, and sends one samples frame over USB CDC. A header frame
 * goes out at start-up, whenever a host opens the port, and once per second. Frame layout:
 * device/PROTOCOL.md; the encoder (src/tactile_frame.c) is tested on the host against the
 * Python encoder.
 *
 * Sample numbering: seq counts timer ticks since power-up. A tick the loop could not serve
 * in time (a USB write held it up) is not made up later with stale readings: the next sample
 * carries the current tick's number, so the host sees a sequence gap of the right size.
 * A failed IMU read likewise loses that sample visibly rather than sending made-up values.
 */
#include <Arduino.h>
#include <Adafruit_TinyUSB.h>  // USB CDC `Serial` on the Adafruit-based nRF52 core
#include <Wire.h>
#include <string.h>

#include "src/pen_info.h"
#include "src/tactile_frame.h"

// ------------------------------------------------------------------------ configuration

// Samples per frame: 1 at 100 Hz (31 bytes per sample on the wire). At high rates, batch
// (<= 32) to cut the per-frame overhead and the number of USB transfers.
#define SAMPLES_PER_FRAME 1

#define PRESSURE_PIN A0  // P0.02 / AIN0
#define IMU_WIRE Wire1   // the Sense's internal I2C bus: P0.07 SDA, P0.27 SCL
#define IMU_ADDR 0x6A    // LSM6DS3TR-C, SA0 tied low on the board

// The sampling timer is TIMER4 (free on this core: the SoftDevice, unused here, would own
// TIMER0). Its handler below is named after it; change both together.
#define SAMPLE_TIMER NRF_TIMER4
#define SAMPLE_TIMER_IRQn TIMER4_IRQn

static const uint32_t PERIOD_US = 1000000u / TP_RATE_HZ;  // 10 000 us at 100 Hz

static_assert(SAMPLES_PER_FRAME >= 1 && SAMPLES_PER_FRAME <= TF_MAX_SAMPLES,
              "SAMPLES_PER_FRAME must be 1..32");
static_assert(1000000u % TP_RATE_HZ == 0, "the rate must divide 1 MHz exactly");
static_assert(TP_N_CHANNELS == 8, "sample layout below assumes the pen's 8 channels");

// LSM6DS3TR-C registers (datasheet DocID030071)
static const uint8_t REG_WHO_AM_I = 0x0F;  // 0x6A (LSM6DS3TR-C) or 0x69 (LSM6DS3)
static const uint8_t REG_CTRL1_XL = 0x10;  // accel: ODR[7:4], full scale[3:2]
static const uint8_t REG_CTRL2_G = 0x11;   // gyro: ODR[7:4], full scale[3:2]
static const uint8_t REG_CTRL3_C = 0x12;   // BDU (bit 6), IF_INC (bit 2), SW_RESET (bit 0)
static const uint8_t REG_OUTX_L_G = 0x22;  // gyro x, y, z then accel x, y, z: 12 bytes, LE
// 104 Hz output rate: the sensor's own digital low-pass (ODR/2) then keeps the band below
// our 50 Hz Nyquist, and reading the latest value every 10 ms skips one sensor sample in 26.
static const uint8_t CTRL1_XL_104HZ_2G = 0x40;    // ODR 104 Hz, +/-2 g (0.061 mg/LSB)
static const uint8_t CTRL2_G_104HZ_250DPS = 0x40; // ODR 104 Hz, +/-250 deg/s (8.75 mdps/LSB)
static const uint8_t CTRL3_C_BDU_INC = 0x44;      // no torn high/low bytes; burst reads
static const uint8_t CTRL3_C_SW_RESET = 0x01;

// ------------------------------------------------------------------------------ state

static volatile uint32_t g_ticks = 0;  // written only by the timer ISR
static uint32_t g_done = 0;            // ticks loop() has dealt with
static uint32_t g_header_tick = 0;
static bool g_header_sent = false;
static bool g_was_connected = false;
static bool g_imu_ok = false;
static uint32_t g_imu_retry_tick = 0;

static uint8_t g_header[TF_MAX_FRAME];  // built once: the header never changes
static size_t g_header_len = 0;

static struct {
    uint32_t seq;
    uint32_t t_us;
    uint8_t n;
    int16_t data[SAMPLES_PER_FRAME * TP_N_CHANNELS];  // sample-major
} g_batch;
static uint8_t g_frame[TF_SAMPLES_FRAME_SIZE(TP_N_CHANNELS, SAMPLES_PER_FRAME)];

// ---------------------------------------------------------------------- timer and clock

// The ISR only counts: the I2C and ADC drivers must not run in interrupt context, and a
// counter (rather than a flag) lets loop() tell how many ticks it missed.
extern "C" void TIMER4_IRQHandler(void)
{
    if (SAMPLE_TIMER->EVENTS_COMPARE[0]) {
        SAMPLE_TIMER->EVENTS_COMPARE[0] = 0;
        SAMPLE_TIMER->CC[0] += PERIOD_US;  // next tick exactly one period on: no drift
        g_ticks = g_ticks + 1;
        (void)SAMPLE_TIMER->EVENTS_COMPARE[0];  // let the clear land before the ISR returns
    }
}

// One free-running 32-bit timer at 1 MHz is both the sample clock (compare channel 0, moved
// on by one period per tick) and the t_us clock (capture channel 1). It wraps at 2^32 us,
// exactly as the protocol's u32 t_us does. (This core's micros() counts FreeRTOS ticks of
// ~1 ms, which is too coarse for sample times; hence the timer.)
static void timer_start()
{
    // Run HFCLK from the 32 MHz crystal (+/-20 ppm) rather than the internal RC oscillator
    // (+/-1.5 % class), so that 100 Hz is 100 Hz. USB needs the crystal anyway.
    NRF_CLOCK->EVENTS_HFCLKSTARTED = 0;
    NRF_CLOCK->TASKS_HFCLKSTART = 1;
    while (!NRF_CLOCK->EVENTS_HFCLKSTARTED) {
    }

    SAMPLE_TIMER->TASKS_STOP = 1;
    SAMPLE_TIMER->TASKS_CLEAR = 1;
    SAMPLE_TIMER->MODE = TIMER_MODE_MODE_Timer;
    SAMPLE_TIMER->BITMODE = TIMER_BITMODE_BITMODE_32Bit;
    SAMPLE_TIMER->PRESCALER = 4;  // 16 MHz / 2^4 = 1 MHz: one count per microsecond
    SAMPLE_TIMER->SHORTS = 0;     // free-running: never cleared, it is also the clock
    SAMPLE_TIMER->CC[0] = PERIOD_US;
    SAMPLE_TIMER->EVENTS_COMPARE[0] = 0;
    SAMPLE_TIMER->INTENSET = TIMER_INTENSET_COMPARE0_Msk;
    NVIC_ClearPendingIRQ(SAMPLE_TIMER_IRQn);
    NVIC_SetPriority(SAMPLE_TIMER_IRQn, 3);
    NVIC_EnableIRQ(SAMPLE_TIMER_IRQn);
    SAMPLE_TIMER->TASKS_START = 1;
}

static uint32_t now_us()
{
    SAMPLE_TIMER->TASKS_CAPTURE[1] = 1;
    return SAMPLE_TIMER->CC[1];
}

// ------------------------------------------------------------------------------ sensors

static bool imu_write(uint8_t reg, uint8_t value)
{
    IMU_WIRE.beginTransmission(IMU_ADDR);
    IMU_WIRE.write(reg);
    IMU_WIRE.write(value);
    return IMU_WIRE.endTransmission() == 0;
}

static bool imu_read(uint8_t reg, uint8_t *buf, uint8_t n)
{
    IMU_WIRE.beginTransmission(IMU_ADDR);
    IMU_WIRE.write(reg);
    if (IMU_WIRE.endTransmission(false) != 0) {  // repeated start
        return false;
    }
    if (IMU_WIRE.requestFrom((uint8_t)IMU_ADDR, n) != n) {
        return false;
    }
    for (uint8_t i = 0; i < n; i++) {
        buf[i] = (uint8_t)IMU_WIRE.read();
    }
    return true;
}

static void imu_power_on()
{
#if defined(PIN_LSM6DS3TR_C_POWER)
    // On the Sense the IMU is supplied from a GPIO (P1.08): drive it in high-drive mode.
    pinMode(PIN_LSM6DS3TR_C_POWER, OUTPUT);
    NRF_P1->PIN_CNF[8] = (GPIO_PIN_CNF_DIR_Output << GPIO_PIN_CNF_DIR_Pos) |
                         (GPIO_PIN_CNF_INPUT_Disconnect << GPIO_PIN_CNF_INPUT_Pos) |
                         (GPIO_PIN_CNF_PULL_Disabled << GPIO_PIN_CNF_PULL_Pos) |
                         (GPIO_PIN_CNF_DRIVE_H0H1 << GPIO_PIN_CNF_DRIVE_Pos) |
                         (GPIO_PIN_CNF_SENSE_Disabled << GPIO_PIN_CNF_SENSE_Pos);
    digitalWrite(PIN_LSM6DS3TR_C_POWER, HIGH);
    delay(50);  // supply ramp and the sensor's boot
#endif
}

static bool imu_begin()
{
    uint8_t id = 0;
    if (!imu_read(REG_WHO_AM_I, &id, 1) || (id != 0x6A && id != 0x69)) {
        return false;
    }
    if (!imu_write(REG_CTRL3_C, CTRL3_C_SW_RESET)) {
        return false;
    }
    for (int i = 0; i < 10; i++) {  // reset takes ~50 us; the bit clears itself
        uint8_t c3 = CTRL3_C_SW_RESET;
        delay(1);
        if (imu_read(REG_CTRL3_C, &c3, 1) && !(c3 & CTRL3_C_SW_RESET)) {
            break;
        }
    }
    return imu_write(REG_CTRL3_C, CTRL3_C_BDU_INC) &&
           imu_write(REG_CTRL1_XL, CTRL1_XL_104HZ_2G) &&
           imu_write(REG_CTRL2_G, CTRL2_G_104HZ_250DPS);
}

// The LSM6DS3TR-C at +/-250 deg/s gives 8.75 mdps per count (114.3 counts per deg/s); the
// pen's header (device/protocol/info.py) says 131 counts per deg/s. Rescale by 0.00875 * 131 =
// 917/800, rounding to nearest; +/-32767 is +/-250.1 deg/s, so the range saturates there.
// (The accelerometer's 0.061 mg/LSB at +/-2 g is the header's 1/16384 g: no rescaling.)
static int16_t gyro_to_header_counts(int16_t raw)
{
    int32_t v = (int32_t)raw * 917;
    v = (v >= 0 ? v + 400 : v - 400) / 800;
    if (v > 32767) {
        v = 32767;
    } else if (v < -32767) {
        v = -32767;
    }
    return (int16_t)v;
}

static int16_t pressure_counts()
{
    int v = analogRead(PRESSURE_PIN);  // 12 bits, ratiometric to VDD (see setup)
    if (v < 0) {
        v = 0;  // the SAADC can read slightly below 0 in single-ended mode
    } else if (v > 4095) {
        v = 4095;
    }
    return (int16_t)v;
}

// One sample in the header's channel order: pressure_0, pressure_1, accel_x, accel_y,
// accel_z, gyro_x, gyro_y, gyro_z. False if the IMU did not answer.
static bool read_sample(int16_t *s)
{
    uint8_t b[12];
    if (!imu_read(REG_OUTX_L_G, b, sizeof b)) {
        return false;
    }
    int16_t p = pressure_counts();
    s[0] = p;
    s[1] = p;  // one tip sensor, sent on both pressure channels as the pen paper does
    for (int axis = 0; axis < 3; axis++) {
        int16_t gyro = (int16_t)(uint16_t)(b[2 * axis] | (b[2 * axis + 1] << 8));
        int16_t accel = (int16_t)(uint16_t)(b[6 + 2 * axis] | (b[6 + 2 * axis + 1] << 8));
        s[2 + axis] = accel;
        s[5 + axis] = gyro_to_header_counts(gyro);
    }
    return true;
}

// ------------------------------------------------------------------------------ sending

static void send_header(uint32_t ticks)
{
    Serial.write(g_header, g_header_len);
    g_header_tick = ticks;
    g_header_sent = true;
}

static void flush_batch()
{
    if (g_batch.n == 0) {
        return;
    }
    size_t n = tf_encode_samples(g_batch.seq, g_batch.t_us, TP_N_CHANNELS, g_batch.n,
                                 g_batch.data, g_frame, sizeof g_frame);
    if (n != 0) {
        Serial.write(g_frame, n);  // dropped by the core when no host has the port open
    }
    g_batch.n = 0;
}

static void add_sample(uint32_t seq, uint32_t t_us, const int16_t *sample)
{
    if (g_batch.n > 0 && seq != g_batch.seq + g_batch.n) {
        flush_batch();  // a frame holds consecutive samples only
    }
    if (g_batch.n == 0) {
        g_batch.seq = seq;
        g_batch.t_us = t_us;
    }
    memcpy(&g_batch.data[g_batch.n * TP_N_CHANNELS], sample, sizeof(int16_t) * TP_N_CHANNELS);
    if (++g_batch.n == SAMPLES_PER_FRAME) {
        flush_batch();
    }
}

static void led(bool on)
{
#if defined(LED_RED)
    digitalWrite(LED_RED, on ? LOW : HIGH);  // active low
#else
    (void)on;
#endif
}

// ------------------------------------------------------------------------ setup and loop

void setup()
{
#if defined(LED_RED)
    pinMode(LED_RED, OUTPUT);
#endif
    led(false);
    Serial.begin(115200);  // USB CDC: the baud rate is ignored; no waiting for a host

    analogReference(AR_VDD4);  // full scale = VDD: the divider reads the same at any supply
    analogReadResolution(12);  // 0..4095 counts

    g_header_len = tf_encode_header(&TP_HEADER, g_header, sizeof g_header);
    if (g_header_len == 0) {  // pen_info.h is wrong: a build error, shown on the LED
        for (;;) {
            led(true);
            delay(100);
            led(false);
            delay(100);
        }
    }

    imu_power_on();
    IMU_WIRE.begin();
    IMU_WIRE.setClock(400000);  // 12-byte burst in ~0.35 ms
    g_imu_ok = imu_begin();
    led(!g_imu_ok);

    timer_start();
}

void loop()
{
    uint32_t ticks = g_ticks;  // one aligned 32-bit load: atomic on the Cortex-M4

    bool connected = (bool)Serial;  // DTR: a host has opened the port
    if (connected && !g_was_connected) {
        send_header(ticks);  // a new reader learns what we are at once
    }
    g_was_connected = connected;

    if (ticks == g_done) {
        return;  // nothing due yet
    }
    g_done = ticks;
    uint32_t seq = ticks - 1u;  // tick 1 is sample 0; skipped ticks leave a gap in seq

    if (!g_imu_ok) {  // no IMU, no samples (the host sees the gap); retry once a second
        if (ticks - g_imu_retry_tick >= TP_RATE_HZ) {
            g_imu_retry_tick = ticks;
            g_imu_ok = imu_begin();
            led(!g_imu_ok);
        }
        return;
    }

    uint32_t t_us = now_us();
    int16_t sample[TP_N_CHANNELS];
    if (!read_sample(sample)) {
        g_imu_ok = false;
        g_imu_retry_tick = ticks;
        led(true);
        return;
    }
    if (!g_header_sent || ticks - g_header_tick >= TP_RATE_HZ) {
        send_header(ticks);
    }
    add_sample(seq, t_us, sample);
}
