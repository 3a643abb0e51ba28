"""The sensor line protocol survives garbage, cuts, overlong lines and bad checksums."""

from __future__ import annotations

import random

from dammrl_core.intent.pad.protocol import MAX_LINE, Frame, FrameParser, checksum, encode_frame


def test_a_frame_round_trips_and_reads_like_nmea() -> None:
    line = encode_frame(42, 1234)
    assert line == b"$P,42,1234*" + f"{checksum(b'P,42,1234'):02X}".encode() + b"\r\n"
    assert FrameParser().feed(line) == [Frame(42, 1234)]


def test_frames_split_anywhere_are_reassembled() -> None:
    stream = b"".join(encode_frame(k, 100 + k) for k in range(50))
    parser, frames = FrameParser(), []
    rng = random.Random(0)
    i = 0
    while i < len(stream):
        n = rng.randint(1, 7)
        frames += parser.feed(stream[i : i + n])
        i += n
    assert frames == [Frame(k, 100 + k) for k in range(50)]
    assert not parser.errors


def test_garbage_between_frames_is_counted_and_skipped() -> None:
    parser = FrameParser()
    frames = parser.feed(b"\x00\xffnoise" + encode_frame(1, 10) + b"junk\n" + encode_frame(2, 20))
    assert frames == [Frame(1, 10), Frame(2, 20)]
    assert parser.errors["garbage"] == len(b"\x00\xffnoise") + len(b"junk")


def test_a_corrupted_byte_fails_the_checksum() -> None:
    line = bytearray(encode_frame(7, 777))
    line[5] ^= 0x04  # flip one bit of the seq digits
    parser = FrameParser()
    assert parser.feed(bytes(line) + encode_frame(8, 800)) == [Frame(8, 800)]
    assert parser.errors["checksum"] == 1


def test_a_cut_frame_is_dropped_when_the_next_one_starts() -> None:
    parser = FrameParser()
    assert parser.feed(encode_frame(1, 10)[:6] + encode_frame(2, 20)) == [Frame(2, 20)]
    assert parser.errors["partial"] == 1


def test_an_overlong_line_is_dropped_whole() -> None:
    parser = FrameParser()
    frames = parser.feed(b"$P," + b"9" * (MAX_LINE * 3) + b"*00\r\n" + encode_frame(3, 30))
    assert frames == [Frame(3, 30)] and parser.errors["overlong"] == 1


def test_values_out_of_range_and_malformed_lines_are_refused() -> None:
    parser = FrameParser()
    for body in (b"P,1,5000", b"P,70000,1", b"Q,1,1", b"P,1", b"P,a,1"):
        parser.feed(b"$" + body + f"*{checksum(body):02X}\r\n".encode())
    parser.feed(b"$P,1,1\r\n$P,1,1*ZZ\r\n")
    assert parser.frames == 0
    assert parser.errors["out of range"] == 2 and parser.errors["malformed"] == 5
