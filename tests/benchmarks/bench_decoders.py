"""Decoder throughput on mixed traffic with 10 % garbage, per protocol and direction.

Not a test (pytest does not collect it): run it and compare with the fastest link of each
protocol; each decoder must keep up with ten times that byte rate.

    .venv/bin/python tests/benchmarks/bench_decoders.py

Traffic is made of the manuals' own example frames (replies and commands), shuffled, with
random garbage bytes making up 10 % of the stream, fed in 64-byte reads like a serial port's.
CAN is fed frame by frame: 10 % of the frames are malformed (wrong length, unknown function).
"""

from __future__ import annotations

import random
import sys
import time

from usage import arguments

from busgate.codecs import ds_servo, inspire_la, zlac706_can, zlac706_rs232
from busgate.codecs.can_frame import CanFrame

SAMPLES = {
    inspire_la: {
        "reply": ["AA 55 04 01 01 62 58 02 C2", "AA 55 03 01 02 37 00 3D",
                  "AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 00 01 08 07 0A 07 94"],
        "command": ["55 AA 04 03 21 37 E8 03 4A", "55 AA 04 03 19 37 E8 03 42",
                    "55 AA 03 01 01 62 02 69", "55 AA 04 01 02 37 14 05 57"],
    },
    ds_servo: {
        "reply": ["FF F5 01 03 00 20 DB", "FF F5 01 02 00 FC", "FF F5 01 04 00 07 FF F4"],
        "command": ["FF FF FE 07 03 2A 08 00 03 E8 DA", "FF FF 01 04 02 38 02 BE",
                    "FF FF FE 0E 83 2A 04 01 07 D0 03 E8 03 07 D0 03 E8 BA"],
    },
    zlac706_rs232: {
        "reply": ["00 00", "02 02", "80000181 e1001cfd e20011f3 e4010ef3 e60000e6 e727101e "
                  "e80000e8 e9271020"],
        "command": ["02 00 D0 D2", "1D 00 A4 C1", "05 27 10 3C", "80 00 80"],
    },
}
CAN_SAMPLES = {
    "reply": ["001#00fb00190000003f", "001#00fe00200001e1e2", "001#00fe0021001e043f",
              "001#00ff00eb08080808"],
    "command": ["001#00fa00190000003f", "001#00fa0011fffff556", "001#00fa00160001e240"],
}
FASTEST_LINK_BYTES_S = {  # 10 bits per byte on a UART
    inspire_la: 921_600 / 10,
    ds_servo: 1_000_000 / 10,  # DS servos run at up to 1 Mbaud; the manual states no rate
    zlac706_rs232: 115_200 / 10,  # the manual states no rate; 115200 is the usual top
}
CAN_FRAMES_S = 500_000 / 111  # the most 8-byte frames 500 kbit/s can carry (no stuffing)
TOTAL_BYTES = 2_000_000
READ_SIZE = 64


def stream(frames: list[bytes], rng: random.Random) -> bytes:
    parts, size, garbage = [], 0, 0
    while size < TOTAL_BYTES:
        if garbage < size * 0.1:
            noise = rng.randbytes(rng.randint(1, 12))
            garbage += len(noise)
            parts.append(noise)
        else:
            parts.append(rng.choice(frames))
        size += len(parts[-1])
    return b"".join(parts)


def time_stream(decoder_class, data: bytes) -> tuple[float, int]:
    decoder = decoder_class()
    events = 0
    started = time.perf_counter()
    for offset in range(0, len(data), READ_SIZE):
        decoder.feed(data[offset : offset + READ_SIZE])
        for _ in decoder.events():
            events += 1
    return time.perf_counter() - started, events


def time_can(decoder_class, frames: list[CanFrame]) -> float:
    decoder = decoder_class()
    started = time.perf_counter()
    for frame in frames:
        decoder.feed(frame)
        for _ in decoder.events():
            pass
    return time.perf_counter() - started


def main() -> int:
    arguments(__doc__)
    rng = random.Random(1)
    worst = float("inf")
    print(f"{'protocol':14} {'direction':9} {'MB/s':>7} {'link KB/s':>9} {'× link':>7}")
    for codec, directions in SAMPLES.items():
        for direction, samples in directions.items():
            data = stream([bytes.fromhex(s) for s in samples], rng)
            decoder = codec.ReplyDecoder if direction == "reply" else codec.CommandDecoder
            seconds, _ = time_stream(decoder, data)
            rate = len(data) / seconds
            ratio = rate / FASTEST_LINK_BYTES_S[codec]
            worst = min(worst, ratio)
            name = codec.__name__.rsplit(".", 1)[1]
            print(f"{name:14} {direction:9} {rate / 1e6:7.2f} "
                  f"{FASTEST_LINK_BYTES_S[codec] / 1e3:9.1f} {ratio:7.0f}")
    for direction, samples in CAN_SAMPLES.items():
        good = [CanFrame.parse(text) for text in samples]
        bad = [CanFrame(1, b"\x00\xfa\x00"), CanFrame(1, bytes.fromhex("0077001900000000"))]
        frames = [rng.choice(bad) if rng.random() < 0.1 else rng.choice(good)
                  for _ in range(200_000)]
        decoder = zlac706_can.ReplyDecoder if direction == "reply" else zlac706_can.CommandDecoder
        rate = len(frames) / time_can(decoder, frames)
        ratio = rate / CAN_FRAMES_S
        worst = min(worst, ratio)
        print(f"{'zlac706_can':14} {direction:9} {rate / 1e3:6.0f}k frames/s vs "
              f"{CAN_FRAMES_S:.0f}/s {ratio:7.0f}")
    print(f"slowest decoder: {worst:.0f} × its fastest link")
    return 0 if worst >= 10 else 1


if __name__ == "__main__":
    sys.exit(main())
