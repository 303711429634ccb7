"""The image writer (device_runtime/image_writer.py): chunks out of order, repeated and
conflicting, the window, verification that discards a bad session, and an incomplete image
that cannot be committed. Resume from the journal and power cuts: test_flash.py."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from flash_helpers import BLOCK, CAPACITY, make_image, sha

from device_runtime.errors import BadChunk, NoImage
from device_runtime.flash import FlashStore


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    return tmp_path / "flash"


def test_out_of_order_duplicate_and_conflicting_chunks(folder):
    image = make_image(8, 5 * BLOCK + 123)
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    writer = store.begin_image(size_bytes=len(image), sha256=sha(image), image_generation=1,
                               window_bytes=2 * BLOCK)
    step = 5000
    offsets = list(range(0, len(image), step))
    rng = random.Random(0)
    for first in range(0, len(offsets), 8):  # 40 KB groups, shuffled, inside the window
        group = offsets[first:first + 8]
        rng.shuffle(group)
        for offset in group:
            assert writer.write_chunk(offset, image[offset:offset + step]) == writer.next_offset
        writer.write_chunk(group[0], image[group[0]:group[0] + step])  # duplicate: fine
        assert writer.next_offset == min(offsets[first] + 8 * step, len(image))
    assert writer.next_offset == len(image)
    with pytest.raises(BadChunk, match="differ from the bytes received there"):
        writer.write_chunk(100, b"\x00" * 10 if image[100:110] != b"\x00" * 10 else b"\x01" * 10)
    with pytest.raises(BadChunk, match="runs past the image size"):
        writer.write_chunk(len(image) - 5, b"123456")
    assert writer.verify()


def test_chunk_beyond_window_refused(folder):
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    writer = store.begin_image(size_bytes=CAPACITY, sha256=bytes(32), image_generation=1,
                               window_bytes=BLOCK)
    with pytest.raises(BadChunk, match=rf"beyond the window \(next_offset 0 \+ {BLOCK} bytes\)"):
        writer.write_chunk(BLOCK, b"x")
    writer.write_chunk(BLOCK - 1, b"x")
    with pytest.raises(TypeError):
        writer.write_chunk("0", b"x")


def test_verify_failure_discards_session(folder):
    image = make_image(9, 3 * BLOCK)
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    writer = store.begin_image(size_bytes=len(image), sha256=sha(image), image_generation=1)
    writer.write_chunk(0, image[:-1] + bytes([image[-1] ^ 1]))
    assert not writer.verify()
    assert writer.closed
    assert store.image_status(sha(image)) == 0
    with pytest.raises(NoImage, match="no image session"):
        store.commit_test()


def test_incomplete_image_cannot_be_committed(folder):
    image = make_image(10, 3 * BLOCK)
    store = FlashStore.open(folder, capacity_bytes=CAPACITY)
    writer = store.begin_image(size_bytes=len(image), sha256=sha(image), image_generation=1)
    writer.write_chunk(0, image[:BLOCK])
    assert not writer.verify() and not writer.closed
    with pytest.raises(NoImage, match=rf"received {BLOCK} of {len(image)} bytes"):
        store.commit_test()
