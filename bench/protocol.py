"""Protocol figures: bytes per sample on the wire, highest sample rate per link, decoder speed.

Run: python bench/protocol.py
"""

from __future__ import annotations

import time

import numpy as np

from tactile.device.protocol import StreamDecoder, encode_header, encode_samples, pen_info

BITS_PER_BYTE = 10  # 8N1 UART: start + 8 data + stop


def stream(n: int, per_frame: int, seed: int = 0) -> bytes:
    """n samples of the pen's 8 channels, header once per second, as the firmware sends them."""
    info = pen_info()
    rng = np.random.default_rng(seed)
    raw = rng.integers(-2000, 2000, (n, 8)).astype(np.int16)
    out = bytearray()
    for s in range(0, n, per_frame):
        if s % 100 == 0:
            out += encode_header(info)
        out += encode_samples(s, s * 10_000, raw[s : s + per_frame])
    return bytes(out)


def main() -> None:
    header = len(encode_header(pen_info()))
    print(f"header frame: {header} B (sent once a second)")
    print("samples/frame  B/sample   max Hz @115200   max Hz @1000000  (8 channels, header incl.)")
    for k in (1, 2, 4, 8, 32):
        frame = len(encode_samples(0, 0, np.ones((k, 8), np.int16)))
        per_sample = frame / k
        rates = []
        for baud in (115_200, 1_000_000):
            bps = baud / BITS_PER_BYTE
            # header once per second: rate * per_sample + header <= bps
            rates.append((bps - header) / per_sample)
        print(f"{k:13d}  {per_sample:8.2f}   {rates[0]:14.0f}   {rates[1]:15.0f}")

    data = stream(200_000, 1)
    for chunk in (64, 4096):
        dec = StreamDecoder()
        t0 = time.perf_counter()
        for i in range(0, len(data), chunk):
            dec.feed(data[i : i + chunk])
        dt = time.perf_counter() - t0
        assert dec.stats.samples == 200_000 and dec.stats.errors == 0
        print(
            f"decoder, clean stream, {chunk}-byte reads: {len(data) / dt / 1e6:.2f} MB/s, "
            f"{dec.stats.samples / dt:,.0f} samples/s"
        )
    rng = np.random.default_rng(1)
    noisy = bytearray(data)
    flips = rng.integers(0, len(noisy), len(noisy) // 1000)
    for i in flips:
        noisy[i] ^= 1 << int(rng.integers(0, 8))
    dec = StreamDecoder()
    t0 = time.perf_counter()
    for i in range(0, len(noisy), 4096):
        dec.feed(bytes(noisy[i : i + 4096]))
    dt = time.perf_counter() - t0
    print(
        f"decoder, 1 bit flip per 1000 bytes: {len(noisy) / dt / 1e6:.2f} MB/s; "
        f"{dec.stats.samples} of 200000 samples kept, {dec.stats.crc_errors} CRC errors, "
        f"{dec.stats.malformed} malformed"
    )


if __name__ == "__main__":
    main()
