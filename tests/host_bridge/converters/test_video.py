"""Compressed video -> Rerun VideoStream, with real streams from PyAV's encoders (libx264,
libx265, SVT-AV1, libvpx): the samples Rerun receives are the bytes sent, with the codec, the
keyframes and the timestamps, and they decode (PyAV again) back to the pictures encoded.

H.264 and H.265 are encoded losslessly, so the decoded pictures must equal the encoded ones
exactly; AV1/VP8/VP9 are lossy here and are checked on bytes and keyframes only.
"""

from __future__ import annotations

import dataclasses
import fractions
import functools
import logging
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import av
import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr
import rerun.blueprint as rrb
from rosbags.rosbag2 import StoragePlugin, Writer

from host_bridge.cli import main as host_main
from host_bridge.converters.images import convert_compressed_image
from host_bridge.converters.video import (
    COMPRESSED_VIDEO,
    VideoTopic,
    VideoTopicState,
    convert_compressed_video,
    video_codec,
)
from host_bridge.core.contract import ColumnsItem, ConvertContext, LogEntry, LogItem
from host_bridge.core.destinations import SinkOptions
from host_bridge.core.schemas import base_typestore
from host_bridge.core.state import TopicState
from host_bridge.errors import ConvertError
from host_bridge.outputs.blueprint import TopicEntry, build_blueprint
from host_bridge.outputs.sink import RerunSink
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.table.registry import default_registry
from robot_relay.wire import RawMessage
from tests.host_bridge.sensor_test_support import convert, convert_run, flat, make_ctx
from tests.rrd import entity_rows

STORE = base_typestore()  # ROS 2 Humble plus the bundled foxglove_msgs definition
T = STORE.types
ROBOT = "bot"
WIDTH, HEIGHT, FRAMES, GOP = 64, 48, 30, 10
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 33_333_333
STAMPS = [T0_NS + i * PERIOD_NS for i in range(FRAMES)]
H264, H265 = rr.VideoCodec.H264, rr.VideoCodec.H265

# codec -> (PyAV encoder, its options, PyAV decoder). The H.26x ones are lossless; every encoder
# runs without B-frames (Rerun's VideoStream presents samples in arrival order).
ENCODERS: dict[rr.VideoCodec, tuple[str, dict[str, str], str]] = {
    H264: ("libx264", {"qp": "0", "x264-params": f"keyint={GOP}:min-keyint={GOP}:scenecut=0:bframes=0"},
           "h264"),
    H265: ("libx265", {"x265-params": f"lossless=1:keyint={GOP}:min-keyint={GOP}:scenecut=0:bframes=0"
                                      ":log-level=error"}, "hevc"),
    rr.VideoCodec.AV1: ("libsvtav1", {"svtav1-params": f"keyint={GOP}:pred-struct=1:lp=1"}, "libdav1d"),
    rr.VideoCodec.VP9: ("libvpx-vp9", {"lag-in-frames": "0"}, "libvpx-vp9"),
    rr.VideoCodec.VP8: ("libvpx", {"lag-in-frames": "0"}, "libvpx"),
}


@dataclass(frozen=True)
class Stream:
    codec: rr.VideoCodec
    pictures: list[npt.NDArray[np.uint8]]  # yuv420p planes, (HEIGHT * 3 / 2, WIDTH)
    packets: list[bytes]
    keyframes: list[bool]  # as the encoder flagged its packets


def picture(i: int) -> npt.NDArray[np.uint8]:
    """A gradient sliding right, a bright square moving down, chroma changing per frame."""
    planes = np.empty((HEIGHT * 3 // 2, WIDTH), dtype=np.uint8)
    planes[:HEIGHT] = (np.arange(WIDTH)[None, :] * 3 + i * 5) % 200
    planes[i % (HEIGHT - 8) : i % (HEIGHT - 8) + 8, 20:28] = 235
    planes[HEIGHT:] = 100 + i
    return planes


@functools.cache
def encode(codec: rr.VideoCodec) -> Stream:
    encoder, options, _ = ENCODERS[codec]
    context: Any = av.CodecContext.create(encoder, "w")
    context.width, context.height, context.pix_fmt = WIDTH, HEIGHT, "yuv420p"
    context.time_base, context.framerate = fractions.Fraction(1, 30), 30
    context.gop_size, context.max_b_frames = GOP, 0
    context.options = options
    pictures = [picture(i) for i in range(FRAMES)]
    packets: list[Any] = []
    for i, planes in enumerate(pictures):
        frame = av.VideoFrame.from_ndarray(planes, format="yuv420p")
        frame.pts = i
        packets.extend(context.encode(frame))
    packets.extend(context.encode(None))
    assert len(packets) == FRAMES
    return Stream(codec, pictures, [bytes(p) for p in packets], [bool(p.is_keyframe) for p in packets])


def decode(codec: rr.VideoCodec, samples: Sequence[bytes]) -> list[npt.NDArray[np.uint8]]:
    context: Any = av.CodecContext.create(ENCODERS[codec][2], "r")
    frames = [f for s in samples for f in context.decode(av.Packet(s))]
    frames.extend(context.decode(None))
    return [f.to_ndarray(format="yuv420p") for f in frames]


# --- messages and what the converters return -----------------------------------------------------


def time_msg(ns: int) -> Any:
    return T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def compressed_image(fmt: str, data: bytes, ns: int) -> Any:
    header = T["std_msgs/msg/Header"](stamp=time_msg(ns), frame_id="camera_optical_frame")
    return T["sensor_msgs/msg/CompressedImage"](
        header=header, format=fmt, data=np.frombuffer(data, np.uint8)
    )


def compressed_video(fmt: str, data: bytes, ns: int) -> Any:
    return T[COMPRESSED_VIDEO](
        timestamp=time_msg(ns), frame_id="camera_optical_frame", format=fmt,
        data=np.frombuffer(data, np.uint8),
    )


def contexts(topic: str, stamps: Sequence[int]) -> list[ConvertContext]:
    """One context per message of one topic, sharing the topic's state as the dispatcher does,
    each logged 5 ns after its stamp; ros_time is the message's stamp (its header's, or a
    CompressedVideo's timestamp)."""
    state = TopicState()
    return [make_ctx(topic, robot=ROBOT, topic_state=state, times={"log_time": ns + 5}) for ns in stamps]


@dataclass(frozen=True)
class Logged:
    codecs: list[int]  # statically logged VideoStream codecs
    samples: list[bytes]
    keyframes: list[bool]
    times: dict[str, list[int]]


def column(item: ColumnsItem, component: str) -> list[Any]:
    """One column's rows as Python lists (each row a unit batch: ``[value]``)."""
    (found,) = [c for c in item.columns if c.component_descriptor().component == component]
    return list(found.as_arrow_array().to_pylist())


def logged(entries: Sequence[LogEntry], path: str) -> Logged:
    codecs = [
        int(flat(a.codec)[0])
        for e in entries if isinstance(e, LogItem) and e.path == path and e.static
        for a in e.archetypes if isinstance(a, rr.VideoStream)
    ]
    assert all(e.path == path for e in entries), [e.path for e in entries]
    rows = [e for e in entries if isinstance(e, ColumnsItem)]
    samples = [bytes(s) for r in rows for (s,) in column(r, "VideoStream:sample")]
    keyframes = [k for r in rows for (k,) in column(r, "VideoStream:is_keyframe")]
    names = {name for r in rows for name in r.times}
    times = {n: [int(t) for r in rows for t in r.times[n]] for n in names}
    return Logged(codecs, samples, keyframes, times)


def every_gop_start() -> list[bool]:
    return [i % GOP == 0 for i in range(FRAMES)]


# --- CompressedImage and CompressedVideo ---------------------------------------------------------


@pytest.mark.parametrize(("codec", "fmt"), [(H264, "h264"), (H265, "h265"), (H265, "hevc")])
def test_h26x_compressed_images_become_a_video_stream(codec: rr.VideoCodec, fmt: str) -> None:
    stream = encode(codec)
    assert stream.keyframes == every_gop_start()
    messages = [compressed_image(fmt, p, ns) for p, ns in zip(stream.packets, STAMPS, strict=True)]
    entries = convert_run(convert_compressed_image, messages, contexts("/camera/image/ffmpeg", STAMPS))
    got = logged(entries, f"/{ROBOT}/camera/image/ffmpeg")
    assert got.codecs == [codec.value]
    assert got.samples == stream.packets  # byte for byte, never decoded or re-encoded
    assert got.keyframes == every_gop_start()
    assert got.times == {"ros_time": STAMPS, "log_time": [ns + 5 for ns in STAMPS]}
    decoded = decode(codec, got.samples)
    assert len(decoded) == FRAMES
    for sent, shown in zip(stream.pictures, decoded, strict=True):
        np.testing.assert_array_equal(shown, sent)


@pytest.mark.parametrize("codec", list(ENCODERS), ids=lambda c: c.name)
def test_foxglove_compressed_video_of_every_codec(codec: rr.VideoCodec) -> None:
    stream = encode(codec)
    fmt = codec.name.lower()  # Foxglove's spelling: h264, h265, av1, vp8, vp9
    messages = [compressed_video(fmt, p, ns) for p, ns in zip(stream.packets, STAMPS, strict=True)]
    entries = convert_run(convert_compressed_video, messages, contexts("/camera/video", STAMPS))
    got = logged(entries, f"/{ROBOT}/camera/video")
    assert got.codecs == [codec.value]
    assert got.samples == stream.packets
    assert got.keyframes == stream.keyframes
    assert got.keyframes[0]
    assert got.times == {"ros_time": STAMPS, "log_time": [ns + 5 for ns in STAMPS]}
    assert len(decode(codec, got.samples)) == FRAMES


def test_message_by_message_equals_the_run_and_logs_the_codec_once() -> None:
    stream = encode(H264)
    ctxs = contexts("/camera/video", STAMPS)
    entries = [
        e for p, ns, c in zip(stream.packets, STAMPS, ctxs, strict=True)
        for e in convert(convert_compressed_video, compressed_video("H264", p, ns), c)
    ]
    got = logged(entries, f"/{ROBOT}/camera/video")
    assert got.codecs == [H264.value]
    assert got.samples == stream.packets
    assert got.keyframes == every_gop_start()
    assert got.times["ros_time"] == STAMPS


def test_restamped_video_keeps_the_receive_based_ros_time() -> None:
    """``restamp: true`` makes ros_time the arrival time; it wins over the message's timestamp."""
    stream = encode(H264)
    restamped = make_ctx("/camera/video", robot=ROBOT, times={"receive_time": 42})
    restamped = dataclasses.replace(restamped, restamp=True)
    entries = convert(convert_compressed_video, compressed_video("h264", stream.packets[0], T0_NS), restamped)
    assert logged(entries, restamped.entity_path).times == {"ros_time": [42], "receive_time": [42]}


# --- parameter sets, keyframes ------------------------------------------------------------------

# (NAL type of a header byte, parameter set types) per codec, as in ITU-T H.264/H.265 table 7-1.
NAL_TYPES: dict[rr.VideoCodec, tuple[Callable[[int], int], set[int]]] = {
    H264: (lambda b: b & 0x1F, {7, 8}), H265: (lambda b: (b >> 1) & 0x3F, {32, 33, 34}),
}


def nal_units(sample: bytes) -> list[bytes]:
    """The NAL units of an Annex B sample, each without its start code."""
    units = [u.strip(b"\x00") for u in sample.split(b"\x00\x00\x01")]
    return [u for u in units if u]


def split_parameter_sets(codec: rr.VideoCodec, sample: bytes) -> tuple[bytes, bytes]:
    """(the parameter sets, the rest) of a sample, each as Annex B."""
    type_of, parameter_sets = NAL_TYPES[codec]
    units = nal_units(sample)
    sets = b"".join(b"\x00\x00\x00\x01" + u for u in units if type_of(u[0]) in parameter_sets)
    rest = b"".join(b"\x00\x00\x00\x01" + u for u in units if type_of(u[0]) not in parameter_sets)
    return sets, rest


@pytest.mark.parametrize("codec", [H264, H265], ids=lambda c: c.name)
def test_parameter_sets_sent_once_go_in_front_of_every_random_access_picture(
    codec: rr.VideoCodec,
) -> None:
    """An encoder that sends SPS/PPS (and VPS) once, in a message of their own, then IDRs
    without them: every IDR Rerun receives carries them again, so the viewer can start (and
    seek) at any keyframe of the recording; the other pictures are untouched."""
    stream = encode(codec)
    sets = split_parameter_sets(codec, stream.packets[0])[0]
    assert sets
    stripped = [split_parameter_sets(codec, p)[1] for p in stream.packets]
    payloads = [sets, *stripped]
    stamps = [T0_NS - PERIOD_NS, *STAMPS]
    messages = [compressed_image(codec.name, p, ns) for p, ns in zip(payloads, stamps, strict=True)]
    got = logged(convert_run(convert_compressed_image, messages, contexts("/cam", stamps)), f"/{ROBOT}/cam")
    assert got.times["ros_time"] == STAMPS  # the parameter sets alone give no sample
    assert got.keyframes == every_gop_start()
    for i, (sample, sent) in enumerate(zip(got.samples, stripped, strict=True)):
        if i % GOP:
            assert sample == sent
        else:
            assert split_parameter_sets(codec, sample) == (sets, sent)
    # A decoder that starts at the second keyframe, with no state, shows the pictures from there.
    decoded = decode(codec, got.samples[GOP:])
    assert len(decoded) == FRAMES - GOP
    for sent_picture, shown in zip(stream.pictures[GOP:], decoded, strict=True):
        np.testing.assert_array_equal(shown, sent_picture)


def test_an_idr_without_any_known_parameter_sets_is_logged_as_is_and_not_a_keyframe() -> None:
    """A host that joined after the only SPS/PPS went by cannot repair the stream: the samples
    are kept (a later keyframe with its own parameter sets makes them decodable)."""
    stream = encode(H264)
    stripped = [split_parameter_sets(H264, p)[1] for p in stream.packets]
    messages = [compressed_image("h264", p, ns) for p, ns in zip(stripped, STAMPS, strict=True)]
    got = logged(convert_run(convert_compressed_image, messages, contexts("/cam", STAMPS)), f"/{ROBOT}/cam")
    assert got.samples == stripped
    assert got.keyframes == [False] * FRAMES


def test_length_prefixed_avcc_samples_are_refused_naming_the_topic() -> None:
    units = nal_units(encode(H264).packets[0])
    avcc = b"".join(len(u).to_bytes(4, "big") + u for u in units)
    msg = compressed_video("h264", avcc, T0_NS)
    ctx = contexts("/camera/video", [T0_NS])[0]
    with pytest.raises(ConvertError) as caught:
        convert(convert_compressed_video, msg, ctx)
    assert str(caught.value) == (
        f"/camera/video: H264 sample of {len(avcc)} bytes does not start with an Annex B start "
        "code (00 00 01); Rerun needs Annex B, not the length-prefixed AVCC/HVCC form of MP4 "
        "files: configure the encoder or transport for Annex B"
    )
    assert ctx.state(VideoTopic).committed == VideoTopicState()  # as the topic started


def test_a_codec_change_is_refused_and_a_failed_run_leaves_the_topic_state_as_it_was() -> None:
    h264, h265 = encode(H264).packets[0], encode(H265).packets[0]
    messages = [compressed_video("h264", h264, STAMPS[0]), compressed_video("h265", h265, STAMPS[1])]
    ctxs = contexts("/camera/video", STAMPS[:2])
    with pytest.raises(ConvertError):
        convert_run(convert_compressed_video, messages, ctxs)
    # The dispatcher retries message by message from here: the state is as the topic started.
    assert ctxs[0].state(VideoTopic).committed == VideoTopicState()
    first = logged(convert(convert_compressed_video, messages[0], ctxs[0]), "/bot/camera/video")
    assert (first.codecs, first.samples) == ([H264.value], [h264])
    with pytest.raises(ConvertError) as caught:
        convert(convert_compressed_video, messages[1], ctxs[1])
    assert str(caught.value) == (
        "/camera/video: video codec changed from H264 to H265; Rerun decodes one codec per "
        "entity, so the H265 samples are dropped (publish the new stream on its own topic)"
    )
    assert ctxs[1].state(VideoTopic).committed.codec == H264


@pytest.mark.parametrize("codec", [H264, rr.VideoCodec.VP9], ids=lambda c: c.name)
def test_an_empty_message_is_refused(codec: rr.VideoCodec) -> None:
    ctx = contexts("/camera/video", [T0_NS])[0]
    with pytest.raises(ConvertError) as caught:
        convert(convert_compressed_video, compressed_video(codec.name, b"", T0_NS), ctx)
    assert str(caught.value) == (
        f"/camera/video: {codec.name} message holds no data; there is no picture to show"
    )


def test_unknown_compressed_video_format_is_refused() -> None:
    ctx = contexts("/camera/video", [T0_NS])[0]
    with pytest.raises(ConvertError) as caught:
        convert(convert_compressed_video, compressed_video("mjpeg", b"\xff\xd8\xff", T0_NS), ctx)
    assert str(caught.value) == (
        "/camera/video: CompressedVideo format 'mjpeg' is not a codec Rerun decodes "
        "(h264/avc, h265/hevc, av1, vp8, vp9); its frames are dropped"
    )


@pytest.mark.parametrize(
    ("fmt", "codec"),
    [
        ("h264", H264), ("H264", H264), ("H.264", H264), ("avc1", H264), ("libx264", H264),
        ("h264_nvenc", H264), ("h264_v4l2m2m", H264), ("rgb8; h264", H264),
        ("h265", H265), ("HEVC", H265), ("hevc_nvenc", H265), ("libx265", H265), ("hev1", H265),
        ("av1", rr.VideoCodec.AV1), ("libsvtav1", rr.VideoCodec.AV1),
        ("libaom-av1", rr.VideoCodec.AV1), ("vp9", rr.VideoCodec.VP9),
        ("libvpx-vp9", rr.VideoCodec.VP9), ("VP8", rr.VideoCodec.VP8),
        ("jpeg", None), ("png", None), ("16UC1; compressedDepth rvl", None), ("", None),
        ("theora", None),
    ],
)
def test_format_spellings(fmt: str, codec: rr.VideoCodec | None) -> None:
    assert video_codec(fmt) == codec


def test_registered_and_shown_in_a_2d_view() -> None:
    assert default_registry().get(COMPRESSED_VIDEO) is convert_compressed_video
    topic = TopicEntry(ROBOT, "/camera/video", COMPRESSED_VIDEO, f"/{ROBOT}/camera/video")
    blueprint = build_blueprint([topic])
    found: list[rrb.View] = []
    parts: list[Any] = [blueprint.root_container]
    while parts:
        part = parts.pop()
        if isinstance(part, rrb.View):
            found.append(part)
        else:
            parts.extend(part.contents)
    assert [v.origin for v in found if isinstance(v, rrb.Spatial2DView)] == [f"/{ROBOT}/camera/video"]


def test_single_message_compressed_image_path_is_the_run_of_one() -> None:
    stream = encode(H265)
    ctx = contexts("/cam", STAMPS[:1])[0]
    entries = convert(convert_compressed_image, compressed_image("hevc", stream.packets[0], T0_NS), ctx)
    got = logged(entries, "/bot/cam")
    assert (got.codecs, got.samples, got.keyframes) == ([H265.value], stream.packets[:1], [True])


# --- through the dispatcher ---------------------------------------------------------------------


def test_a_bad_message_in_a_video_run_costs_only_itself_and_is_warned_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """One run of a topic: H.264 pictures with two messages of an unknown format among them.
    The dispatcher retries the failed run message by message: the pictures all arrive, the codec
    once, and the user sees one warning naming the topic and the format."""
    packets = encode(H264).packets[:5]
    formats = ["h264", "theora", "h264", "theora", "h264"]
    payloads = [p if f == "h264" else b"\x00\x00\x01\x00" for p, f in zip(packets, formats, strict=True)]
    messages = [compressed_image(f, p, ns) for f, p, ns in zip(formats, payloads, STAMPS, strict=False)]
    batch = [
        RawMessage(ROBOT, "/cam", m.__msgtype__, bytes(STORE.serialize_cdr(m, m.__msgtype__)), log_ns=ns)
        for m, ns in zip(messages, STAMPS, strict=False)
    ]
    dispatcher = Dispatcher(RerunSink(SinkOptions(save=tmp_path / "out.rrd")))
    with caplog.at_level(logging.WARNING):
        dispatcher.dispatch(batch)
    dispatcher.sink.close()
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1
    assert "/cam: CompressedImage format 'theora' is not one Rerun can show" in warnings[0]
    counters = dispatcher.counters[(ROBOT, "/cam")]
    assert (counters.received, counters.converted, counters.dropped) == (5, 3, 2)
    rows = entity_rows(tmp_path / "out.rrd")[f"/{ROBOT}/cam"]
    assert [r["VideoStream:codec"] for r in rows if r["static"]] == [[H264.value]]
    shown = [r for r in rows if r.get("VideoStream:sample")]
    assert [bytes(r["VideoStream:sample"][0]) for r in shown] == [packets[0], packets[2], packets[4]]
    assert [r["ros_time"] for r in shown] == [STAMPS[0], STAMPS[2], STAMPS[4]]


# --- a real bag through swanky-host --------------------------------------------------------------


def write_video_bag(path: Path) -> None:
    h264, h265 = encode(H264), encode(H265)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        image = writer.add_connection("/camera/image/h264", "sensor_msgs/msg/CompressedImage",
                                      typestore=STORE)
        video = writer.add_connection("/camera/video", COMPRESSED_VIDEO, typestore=STORE)
        for a, b, ns in zip(h264.packets, h265.packets, STAMPS, strict=True):
            for connection, msg in ((image, compressed_image("h264", a, ns)),
                                    (video, compressed_video("h265", b, ns))):
                writer.write(connection, ns + 1_000_000, STORE.serialize_cdr(msg, msg.__msgtype__))


@pytest.mark.integration
def test_bag_with_both_video_kinds_through_swanky_host_and_rerun_mcap_convert(tmp_path: Path) -> None:
    """``swanky-host --bag ... --save out.rrd`` on a rosbag2 MCAP holding H.264 CompressedImage
    and H.265 foxglove CompressedVideo, read back; and Rerun's own importer on the same file:
    it shows the H.264 CompressedImage with the same samples, and (rerun 0.41) leaves the ROS 2
    CompressedVideo an undecoded message."""
    write_video_bag(tmp_path / "bag")
    assert host_main(["--bag", str(tmp_path / "bag"), "--robot", ROBOT,
                      "--save", str(tmp_path / "out.rrd"), "--strict"]) == 0
    rows = entity_rows(tmp_path / "out.rrd")
    for topic, stream in (("/camera/image/h264", encode(H264)), ("/camera/video", encode(H265))):
        entity = rows[f"/{ROBOT}{topic}"]
        assert [r["VideoStream:codec"] for r in entity if r["static"]] == [[stream.codec.value]]
        samples = [r for r in entity if not r["static"]]
        assert [bytes(r["VideoStream:sample"][0]) for r in samples] == stream.packets
        assert [r["VideoStream:is_keyframe"] for r in samples] == [[k] for k in every_gop_start()]
        assert [r["ros_time"] for r in samples] == STAMPS
        assert [r["log_time"] for r in samples] == [ns + 1_000_000 for ns in STAMPS]

    (mcap,) = (tmp_path / "bag").glob("*.mcap")
    rerun = Path(sys.executable).parent / "rerun"
    subprocess.run([str(rerun), "mcap", "convert", str(mcap), "-o", str(tmp_path / "rerun.rrd")],
                   check=True, capture_output=True, timeout=120)
    theirs = entity_rows(tmp_path / "rerun.rrd")
    their_samples = [bytes(r["VideoStream:sample"][0]) for r in theirs["/camera/image/h264"]
                     if r.get("VideoStream:sample")]
    assert their_samples == encode(H264).packets
    assert not any(r.get("VideoStream:sample") for r in theirs["/camera/video"])
