"""tactile.device.protocol: the wire protocol (``device/PROTOCOL.md``).

:mod:`~tactile.device.protocol.info` says what a device is (channels, units, rate); the codec
(:mod:`~tactile.device.protocol.codec`) turns samples and headers into COBS frames with a CRC and
back; :class:`StreamDecoder` turns any bytes from a port into samples, headers and gaps::

    from tactile.device.protocol import StreamDecoder
    events = StreamDecoder().feed(data)

:mod:`~tactile.device.protocol.vectors` reads and writes the test vectors the C encoder shares.
"""

from tactile.device.protocol.codec import (
    MAX_ENCODED,
    SEQ_MODULO,
    SUPPORTED_VERSIONS,
    WIRE_MAX_CHANNELS,
    HeaderFrame,
    SamplesFrame,
    cobs_decode,
    cobs_encode,
    crc16,
    encode_header,
    encode_samples,
    find_frame,
    parse_frame,
)
from tactile.device.protocol.decoder import REPLAY_WINDOW, Mode, StreamDecoder, decode
from tactile.device.protocol.events import DecoderStats, Event, Gap, Header, Samples
from tactile.device.protocol.info import (
    MAX_CHANNELS,
    PEN_CHANNELS,
    PEN_RATE_HZ,
    PROTOCOL_VERSION,
    ChannelSpec,
    DeviceInfo,
    f32,
    pen_info,
)

__all__ = [
    "ChannelSpec", "DecoderStats", "DeviceInfo", "Event", "Gap", "Header", "HeaderFrame",
    "MAX_CHANNELS", "MAX_ENCODED", "Mode", "PEN_CHANNELS", "PEN_RATE_HZ", "PROTOCOL_VERSION",
    "REPLAY_WINDOW", "SEQ_MODULO", "SUPPORTED_VERSIONS", "Samples", "SamplesFrame",
    "StreamDecoder", "WIRE_MAX_CHANNELS", "cobs_decode", "cobs_encode", "crc16", "decode",
    "encode_header", "encode_samples", "f32", "find_frame", "parse_frame", "pen_info",
]
