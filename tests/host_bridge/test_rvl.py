"""The RVL codec (:mod:`host_bridge.core.rvl`) against a reference encoder written from
image_transport's RvlCodec, driven through compressedDepth ``rvl`` CompressedImages: every run
and code length round-trips, and a 32FC1 payload's de-quantized depth is exact."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr

from tests.host_bridge.converters.test_images import (
    RNG_SEED,
    H,
    W,
    convert_compressed,
    depth_header,
    make_compressed,
    pylist,
    quantize_inverse_depth,
    random_pixels,
    received_pixels,
)


def rvl_encode(values: npt.NDArray[np.uint16]) -> bytes:
    """Reference RVL encoder, written from image_transport's RvlCodec::CompressRVL."""
    nibbles: list[int] = []

    def vle(value: int) -> None:
        while True:
            nibble, value = value & 7, value >> 3
            nibbles.append(nibble | (8 if value else 0))
            if not value:
                return

    flat = [int(v) for v in values.ravel()]
    previous = i = 0
    while i < len(flat):
        start = i
        while i < len(flat) and flat[i] == 0:
            i += 1
        vle(i - start)
        start = i
        while i < len(flat) and flat[i] != 0:
            i += 1
        vle(i - start)
        for value in flat[start:i]:
            delta = value - previous
            vle(((delta << 1) ^ (delta >> 31)) & 0xFFFFFFFF)
            previous = value
    nibbles += [0] * (-len(nibbles) % 8)
    words = [int("".join(f"{n:x}" for n in nibbles[k : k + 8]), 16) for k in range(0, len(nibbles), 8)]
    return np.asarray(words, dtype="<u4").tobytes()


def rvl_payload(values: npt.NDArray[np.uint16], quant: tuple[float, float] = (0.0, 0.0)) -> bytes:
    height, width = values.shape
    size = np.asarray([width, height], dtype="<u4").tobytes()
    return depth_header(*quant) + size + rvl_encode(values)


def holey_depth(height: int, width: int) -> npt.NDArray[np.uint16]:
    """Smooth depth with holes, saturated and far values: every RVL run and code length."""
    rng = np.random.default_rng(RNG_SEED)
    yy, xx = np.mgrid[0:height, 0:width]
    noise = rng.integers(-5, 6, (height, width))
    depth: npt.NDArray[np.uint16] = (800 + 40 * yy + 3 * xx + noise).astype(np.uint16)
    depth[rng.random((height, width)) < 0.2] = 0
    depth[:2] = 0  # a run longer than one row
    depth[-1, -5:] = 0  # image ends in zeros
    depth[5, 10] = 65535
    depth[5, 11] = 1
    return depth


@pytest.mark.parametrize("shape", [(1, 1), (1, 5), (24, 32)])
def test_compressed_depth_rvl_16uc1_round_trips(shape: tuple[int, int]) -> None:
    small = (np.arange(1, shape[0] * shape[1] + 1) * 300).reshape(shape).astype(np.uint16)
    depth = holey_depth(*shape) if shape[0] > 6 else small
    archetype = convert_compressed(make_compressed("16UC1; compressedDepth rvl", rvl_payload(depth)))
    assert isinstance(archetype, rr.DepthImage)
    assert pylist(archetype.meter) == [1000.0]
    np.testing.assert_array_equal(received_pixels(archetype)[..., 0], depth)


def test_compressed_depth_rvl_all_zero_and_32fc1() -> None:
    zeros = np.zeros((4, 6), np.uint16)
    empty = convert_compressed(make_compressed("16UC1; compressedDepth rvl", rvl_payload(zeros)))
    np.testing.assert_array_equal(received_pixels(empty)[..., 0], zeros)

    depth_m = random_pixels((H, W), np.float32)
    inverse, quant_a, quant_b = quantize_inverse_depth(depth_m)
    inverse[2, 2] = 0
    msg = make_compressed("32FC1; compressedDepth rvl", rvl_payload(inverse, (quant_a, quant_b)))
    got = received_pixels(convert_compressed(msg))[..., 0]
    assert np.isnan(got[2, 2])
    valid = inverse > 0
    expected = np.float32(quant_a) / (inverse[valid].astype(np.float32) - np.float32(quant_b))
    np.testing.assert_array_equal(got[valid], expected)
