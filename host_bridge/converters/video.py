"""Compressed video -> Rerun ``VideoStream``, never decoded on the host.

Robots on Wi-Fi send their cameras as video: ``foxglove_msgs/msg/CompressedVideo`` (Foxglove's
schema, definition bundled in ``schemas/msg``) and ``sensor_msgs/msg/CompressedImage`` whose
``format`` names a video codec (Isaac ROS's H.264 encoder, ffmpeg-based image transports, ...).
An H.264 camera is a few Mbit/s (640x480 raw RGB at 30 Hz is 221), so the samples are logged
as they came: one ``VideoStream`` sample per message, the codec logged once, statically, per
entity (as Rerun's own MCAP importer does) and the viewer decodes them.

Why the host still looks inside the samples:

* ``is_keyframe`` travels with every sample, as Rerun defines it: a sample a decoder can start
  from with no prior state. For H.264 that is an IDR picture with its SPS and PPS in the same
  sample; for H.265 an IRAP picture with its VPS, SPS and PPS; for AV1 a key frame after a
  sequence header; for VP8/VP9 a key frame. The viewer only starts decoding (and seeks) at such
  samples.
* Some encoders (a Raspberry Pi's without ``--inline``, NVENC without repeated headers) send the
  H.264/H.265 parameter sets once, alone or with the first picture only. The host remembers the
  latest of each per topic, and a random-access picture sent without them gets them inserted in
  front of its first slice, so every IDR of a recording is a place the viewer can start from.
  A message holding only parameter sets (no picture) gives no sample of its own. This is the only
  time a sample's bytes change; any other sample is logged byte for byte.
* Rerun takes H.264/H.265 as Annex B (start codes), so a length-prefixed (MP4-style AVCC) sample
  is refused with a message saying so instead of showing as a broken video.

A topic keeps the codec of its first sample; samples of another codec are refused (Rerun decodes
one codec per entity). B-frames are not supported by Rerun's VideoStream (the viewer presents
samples in arrival order), so encoders should run without them, as low-latency streaming does.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import rerun as rr

from host_bridge.core.contract import ColumnsItem, LogEntry, LogItem, RowIndex, Run
from host_bridge.errors import ConvertError

COMPRESSED_VIDEO = "foxglove_msgs/msg/CompressedVideo"

# Spellings of each codec in ``format`` fields, after lower-casing, dropping dots, a leading
# "lib" and an ffmpeg hardware suffix ("_nvenc", "_v4l2m2m"): Foxglove's names, WebCodecs
# fourccs and ffmpeg encoder names.
_CODEC_NAMES: dict[str, rr.VideoCodec] = {
    **dict.fromkeys(("h264", "avc", "avc1", "x264", "openh264"), rr.VideoCodec.H264),
    **dict.fromkeys(("h265", "hevc", "hev1", "hvc1", "x265"), rr.VideoCodec.H265),
    **dict.fromkeys(("av1", "av01", "aom-av1", "svtav1", "rav1e"), rr.VideoCodec.AV1),
    **dict.fromkeys(("vp9", "vp09", "vpx-vp9"), rr.VideoCodec.VP9),
    **dict.fromkeys(("vp8", "vp08"), rr.VideoCodec.VP8),
}
CODEC_SPELLINGS = "h264/avc, h265/hevc, av1, vp8, vp9"

_START_CODE = b"\x00\x00\x01"
_LONG_START_CODE = b"\x00\x00\x00\x01"


def video_codec(fmt: str) -> rr.VideoCodec | None:
    """The codec a ``format`` field names, None if it names none.

    Accepts any case and the spellings publishers use (``h264``, ``H.264``, ``hevc``, ``h265``,
    ``libx264``, ``hevc_nvenc``, ``h264_v4l2m2m``, ``avc1``, ...), also as one word of an
    image_transport-style string (``rgb8; h264``).
    """
    for word in re.split(r"[\s;:,/]+", fmt.lower()):
        codec = _CODEC_NAMES.get(word.replace(".", "").removeprefix("lib").split("_")[0])
        if codec is not None:
            return codec
    return None


# --- keyframes -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _NalTypes:
    """What the host needs to know of an Annex B codec's NAL unit types."""

    of_header: Callable[[int], int]
    parameter_sets: tuple[int, ...]  # in the order a decoder needs them
    random_access: frozenset[int]
    pictures: frozenset[int]  # VCL units: a sample without one holds no picture


_ANNEX_B: dict[rr.VideoCodec, _NalTypes] = {
    # H.264 (ITU-T H.264 table 7-1): slices 1-5, IDR 5, SPS 7, PPS 8.
    rr.VideoCodec.H264: _NalTypes(
        of_header=lambda byte: byte & 0x1F,
        parameter_sets=(7, 8),
        random_access=frozenset({5}),
        pictures=frozenset(range(1, 6)),
    ),
    # H.265 (ITU-T H.265 table 7-1): VCL 0-31, IRAP 16-23, VPS 32, SPS 33, PPS 34.
    rr.VideoCodec.H265: _NalTypes(
        of_header=lambda byte: (byte >> 1) & 0x3F,
        parameter_sets=(32, 33, 34),
        random_access=frozenset(range(16, 24)),
        pictures=frozenset(range(32)),
    ),
}


def _vp8_keyframe(data: bytes) -> bool:
    """RFC 6386 9.1: a clear low bit in the frame tag, then the key frame start code."""
    return len(data) >= 6 and not data[0] & 1 and data[3:6] == b"\x9d\x01\x2a"


def _vp9_keyframe(data: bytes) -> bool:
    """VP9 uncompressed header: frame_marker 0b10, profile (and a reserved bit in profile 3),
    show_existing_frame 0, frame_type 0 (KEY_FRAME); all within the first byte."""
    if not data or data[0] >> 6 != 0b10:
        return False
    bits = data[0]
    profile = ((bits >> 5) & 1) | ((bits >> 3) & 2)
    # show_existing_frame and frame_type are the two bits after the profile (and reserved) bits.
    return not (bits >> (1 if profile == 3 else 2)) & 0b11


def _leb128(data: bytes, at: int) -> tuple[int, int]:
    value = 0
    for i in range(8):
        if at + i >= len(data):
            break
        value |= (data[at + i] & 0x7F) << (7 * i)
        if not data[at + i] & 0x80:
            return value, at + i + 1
    return -1, len(data)


def _av1_keyframe(data: bytes) -> bool:
    """A KEY_FRAME frame (header) OBU after a sequence header OBU, Rerun's rule; walks the OBUs
    of the low-overhead bitstream format (AV1 spec 5.2)."""
    at = 0
    reduced_still_picture: bool | None = None
    while at < len(data):
        header = data[at]
        obu_type = (header >> 3) & 0xF
        at += 2 if header & 0b100 else 1  # extension byte
        if header & 0b10:
            size, at = _leb128(data, at)
            if size < 0:
                return False
        else:
            size = len(data) - at
        payload = data[at : at + size]
        at += size
        if not payload:
            continue
        if obu_type == 1:  # OBU_SEQUENCE_HEADER: seq_profile(3) still_picture(1) reduced(1)
            reduced_still_picture = bool(payload[0] & 0b1000)
        # OBU_FRAME_HEADER or OBU_FRAME: a reduced still-picture header has only key frames;
        # otherwise the header starts with show_existing_frame(1) frame_type(2), KEY_FRAME 0.
        elif obu_type in (3, 6) and reduced_still_picture is not None and (
            reduced_still_picture or not payload[0] >> 5
        ):
            return True
    return False


_OTHER_KEYFRAMES: dict[rr.VideoCodec, Callable[[bytes], bool]] = {
    rr.VideoCodec.AV1: _av1_keyframe,
    rr.VideoCodec.VP8: _vp8_keyframe,
    rr.VideoCodec.VP9: _vp9_keyframe,
}


# --- per-topic state -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class VideoTopicState:
    """What a video topic carries from one message to the next.

    Frozen and replaced as a whole, only once a run of messages converted without error: a run
    the dispatcher retries message by message must find the state as it was before the run.
    """

    codec: rr.VideoCodec | None = None  # logged statically; None until the first sample
    parameter_sets: Mapping[int, bytes] = field(default_factory=dict)  # NAL type -> latest unit


@dataclass(slots=True)
class VideoTopic:
    """The topic's state record: the VideoTopicState of the last run that converted."""

    committed: VideoTopicState = field(default_factory=VideoTopicState)


@dataclass(frozen=True, slots=True)
class VideoFrame:
    """One message's video payload and its stamp (a CompressedImage's header stamp, a
    CompressedVideo's ``timestamp``): its ros_time by the run's rule (:meth:`Run.times`)."""

    codec: rr.VideoCodec
    data: npt.NDArray[np.uint8]
    stamp_ns: int


@dataclass(frozen=True, slots=True)
class _Sample:
    data: bytes | npt.NDArray[np.uint8]
    keyframe: bool


def _annex_b_sample(
    state: VideoTopicState, frame: VideoFrame, topic: str
) -> tuple[VideoTopicState, _Sample | None]:
    """Keyframe flag and parameter-set bookkeeping of one H.264/H.265 access unit."""
    types = _ANNEX_B[frame.codec]
    data = frame.data.tobytes()
    first = data.find(_START_CODE)
    if first < 0 or data[:first].strip(b"\x00"):
        msg = (
            f"{topic}: {frame.codec.name} sample of {len(data)} bytes does not start with an "
            "Annex B start code (00 00 01); Rerun needs Annex B, not the length-prefixed "
            "AVCC/HVCC form of MP4 files: configure the encoder or transport for Annex B"
        )
        raise ConvertError(msg)
    # (start code offset, first byte of the unit) of every NAL unit.
    units: list[tuple[int, int]] = []
    at = first
    while at >= 0:
        begin = at + len(_START_CODE)
        units.append((at - 1 if at > 0 and data[at - 1] == 0 else at, begin))
        at = data.find(_START_CODE, begin)
    nal_types = [types.of_header(data[begin]) if begin < len(data) else -1 for _, begin in units]
    parameter_sets = dict(state.parameter_sets)
    for i, nal_type in enumerate(nal_types):
        if nal_type in types.parameter_sets:
            end = units[i + 1][0] if i + 1 < len(units) else len(data)
            # A parameter set ends in its stop bit: zero bytes after it belong to no unit.
            parameter_sets[nal_type] = data[units[i][1] : end].rstrip(b"\x00")
    state = replace(state, parameter_sets=parameter_sets)
    pictures = [i for i, t in enumerate(nal_types) if t in types.pictures]
    if not pictures:
        return state, None  # parameter sets alone: they go in front of the next random access
    present = set(nal_types)
    sample: bytes | npt.NDArray[np.uint8] = frame.data
    random_access = not present.isdisjoint(types.random_access)
    missing = [t for t in types.parameter_sets if t not in present]
    if random_access and missing and all(t in parameter_sets for t in missing):
        insert_at = units[pictures[0]][0]
        inserted = b"".join(_LONG_START_CODE + parameter_sets[t] for t in missing)
        sample = data[:insert_at] + inserted + data[insert_at:]
        present.update(missing)
    keyframe = random_access and present.issuperset(types.parameter_sets)
    return state, _Sample(sample, keyframe)


def _sample(
    state: VideoTopicState, frame: VideoFrame, topic: str
) -> tuple[VideoTopicState, _Sample | None]:
    if state.codec is not None and frame.codec != state.codec:
        msg = (
            f"{topic}: video codec changed from {state.codec.name} to {frame.codec.name}; Rerun "
            f"decodes one codec per entity, so the {frame.codec.name} samples are dropped "
            "(publish the new stream on its own topic)"
        )
        raise ConvertError(msg)
    if frame.data.size == 0:
        msg = f"{topic}: {frame.codec.name} message holds no data; there is no picture to show"
        raise ConvertError(msg)
    state = replace(state, codec=frame.codec)
    if frame.codec in _ANNEX_B:
        return _annex_b_sample(state, frame, topic)
    return state, _Sample(frame.data, _OTHER_KEYFRAMES[frame.codec](frame.data.tobytes()))


def _sample_column(samples: Sequence[bytes | npt.NDArray[np.uint8]]) -> Any:
    """All samples in one Arrow list<uint8> (one copy of the bytes, however many samples).

    Typed Any: ``VideoStream.columns`` takes its own batch type as it is (a list of buffers
    would be copied sample by sample), but its annotation does not list it.
    """
    offsets = np.zeros(len(samples) + 1, dtype=np.int32)
    np.cumsum([len(s) for s in samples], out=offsets[1:])
    values = np.concatenate([np.frombuffer(s, dtype=np.uint8) for s in samples])
    array = pa.ListArray.from_arrays(
        pa.array(offsets), pa.array(values), type=rr.components.VideoSampleBatch._ARROW_DATATYPE
    )
    return rr.components.VideoSampleBatch(array)


def video_entries(run: Run, frames: Sequence[VideoFrame], rows: RowIndex) -> list[LogEntry]:
    """``VideoStream`` rows for the video messages ``rows`` of a run (``frames``, one each):
    one row per picture."""
    topic = run.state(VideoTopic)
    before = state = topic.committed
    samples: list[_Sample] = []
    sampled: list[tuple[int, int]] = []  # the row and stamp of each sample
    for frame, row in zip(frames, rows.tolist(), strict=True):
        state, sample = _sample(state, frame, run.topic)
        if sample is not None:
            samples.append(sample)
            sampled.append((row, frame.stamp_ns))
    entries: list[LogEntry] = []
    if before.codec is None and state.codec is not None:
        entries.append(LogItem(run.entity_path, (rr.VideoStream(codec=state.codec),), static=True))
    if samples:
        sample_rows = np.array([row for row, _ in sampled], np.intp)
        stamps = np.array([stamp for _, stamp in sampled], np.int64)
        for picked, times in run.times(stamps, sample_rows):
            chosen = samples if len(picked) == len(samples) else [samples[i] for i in picked.tolist()]
            columns = rr.VideoStream.columns(
                sample=_sample_column([s.data for s in chosen]),
                is_keyframe=[s.keyframe for s in chosen],
            )
            entries.append(ColumnsItem(run.entity_path, list(columns), times))
    topic.committed = state
    return entries


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _compressed_video_frame(msg: Any, topic: str) -> VideoFrame:
    codec = video_codec(msg.format)
    if codec is None:
        msg_ = (
            f"{topic}: CompressedVideo format {msg.format!r} is not a codec Rerun decodes "
            f"({CODEC_SPELLINGS}); its frames are dropped"
        )
        raise ConvertError(msg_)
    return VideoFrame(codec, msg.data, _stamp_ns(msg.timestamp))


def convert_compressed_video(run: Run) -> list[LogEntry]:
    frames = [_compressed_video_frame(m, run.topic) for m in run.messages()]
    return video_entries(run, frames, np.arange(len(frames)))


SPEC = convert_compressed_video

__all__ = [
    "SPEC",
    "VideoFrame",
    "VideoTopic",
    "VideoTopicState",
    "convert_compressed_video",
    "video_codec",
    "video_entries",
]
