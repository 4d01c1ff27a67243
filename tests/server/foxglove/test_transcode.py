"""The shared frame -> CDR cache: once per frame object, fragments reassembled, bounded."""

from __future__ import annotations

import numpy as np

from fleetctl.server.foxglove import transcode
from fleetctl.server.foxglove.transcode import SharedTranscoder
from fleetctl.wire import fragments
from fleetctl.wire.codec import default_codec
from tests.server.foxglove.conftest import REFERENCE, SCAN_TYPE, scan, scan_frame


def shared() -> SharedTranscoder:
    return SharedTranscoder(default_codec(), 1 << 24, wall_ns=lambda: 42)


def test_one_transcoding_per_frame_object() -> None:
    cache = shared()
    frame = scan_frame("/r/scan", 3)
    first = [cache.convert(frame) for _ in range(5)]
    assert cache.transcoded == 1 and cache.hits == 4
    assert first[0] is not None and all(c is first[0] for c in first)
    got = REFERENCE.deserialize_cdr(first[0].cdr, SCAN_TYPE)
    np.testing.assert_array_equal(got.ranges, scan(3).ranges)
    assert (first[0].type, first[0].receive_time_ns) == (SCAN_TYPE, 42)
    assert cache.convert(bytes(bytearray(frame))) is not None  # equal, another object
    assert cache.transcoded == 2


def test_fragments_complete_once_for_every_viewer() -> None:
    cache = shared()
    whole = scan_frame("/r/scan", 5, 5000)
    parts = fragments.split(whole, topic="/r/scan", message_id=9, max_fragment_bytes=4096,
                            no_drop=False)
    for _viewer in range(3):  # every viewer pops the same fragment objects
        results = [cache.convert(p) for p in parts]
        assert results[:-1] == [None] * (len(parts) - 1)
        assert results[-1] is not None and results[-1].type == SCAN_TYPE
    assert cache.transcoded == len(parts)


def test_garbage_is_counted_not_raised() -> None:
    cache = shared()
    assert cache.convert(b"\x00" * 3) is None and cache.failed == 1


def test_cache_is_bounded() -> None:
    cache = shared()
    frames = [scan_frame("/r/scan", i, 10) for i in range(transcode.MAX_ENTRIES + 10)]
    for frame in frames:
        cache.convert(frame)
    assert len(cache._cache) == transcode.MAX_ENTRIES
