/*
 * pen_info.h - what the pen says about itself in its header frame.
 *
 * Must match device/protocol/info.py (pen_info(): PEN_CHANNELS, PEN_RATE_HZ): the host test compiles
 * this table and checks that its header frame is byte-identical to the Python one.
 */
#ifndef TACTILE_PEN_INFO_H
#define TACTILE_PEN_INFO_H

#include "tactile_frame.h"

#define TP_RATE_HZ 100u
#define TP_N_CHANNELS 8u
#define TP_DEVICE "tactile-pen"

/* Scales: tip ADC 0.01 N per count (nominal, see README); IMU at +/-2 g (16384 LSB/g) and
 * +/-250 deg/s (131 LSB per deg/s, after the firmware's rescaling of the gyro counts). */
#define TP_PRESSURE_SCALE 0.01f
#define TP_ACCEL_SCALE (1.0f / 16384.0f)
#define TP_GYRO_SCALE (1.0f / 131.0f)

static const tf_channel TP_CHANNELS[TP_N_CHANNELS] = {
    {"pressure_0", "N", TP_PRESSURE_SCALE, 0.0f},
    {"pressure_1", "N", TP_PRESSURE_SCALE, 0.0f},
    {"accel_x", "g", TP_ACCEL_SCALE, 0.0f},
    {"accel_y", "g", TP_ACCEL_SCALE, 0.0f},
    {"accel_z", "g", TP_ACCEL_SCALE, 0.0f},
    {"gyro_x", "deg/s", TP_GYRO_SCALE, 0.0f},
    {"gyro_y", "deg/s", TP_GYRO_SCALE, 0.0f},
    {"gyro_z", "deg/s", TP_GYRO_SCALE, 0.0f},
};

static const tf_header TP_HEADER = {
    TF_PROTOCOL_VERSION, (float)TP_RATE_HZ, TP_DEVICE, TP_N_CHANNELS, TP_CHANNELS,
};

#endif /* TACTILE_PEN_INFO_H */
