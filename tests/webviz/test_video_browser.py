"""Video topics in a real headless Chromium: foxglove_msgs/CompressedVideo frames encoded by
PyAV, sent by a robot that is a real WebSocket client through a real relay, decoded by the
page with WebCodecs; a seq gap stops decoding and makes the page ask for a keyframe."""

from __future__ import annotations

import contextlib
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from fleetctl.wire.codec import Codec
from fleetctl.wire.metadata import read_metadata
from tests.webviz.conftest import webviz_server
from tests.webviz.pixels import drawn_fraction_within
from tests.webviz.scripted import KEYFRAME_REQUEST_TYPE, Relay, VideoFeed, scripted_fleet
from tests.webviz.test_browser import PANEL_BG, TIMEOUT_MS, wait_js, watch_errors
from tests.webviz.test_scene_browser import open_robot_page
from tests.webviz.video import encode, h264_codec_string

pytestmark = pytest.mark.browser

TOPIC = "/camera/image_raw"
FULL = f"/r1{TOPIC}"
STATS = f"fleetviz.views.video.stats['{FULL}']"


def stat(name: str) -> str:
    return f"({STATS}?.{name} ?? 0)"


async def send_one(page: Any, feed: VideoFeed, *, skip: bool = False) -> None:
    """Send the next unit and wait until the page has it: the relay keeps only the newest
    frame of a droppable topic per consumer, so a burst would lose frames on purpose."""
    await feed.send_next(skip=skip)
    await wait_js(page, f"fleetviz.conn.health.topics.get('{FULL}')?.received === {feed.pos}")


@contextlib.asynccontextmanager
async def video_page(tmp_path: Path, browser: Any, webviz_factory: list[Any],
                     viewport: dict[str, int]) -> AsyncIterator[tuple[Relay, Any, list[str]]]:
    """A scripted fleet, its page server and a page on r1 subscribed to the video topic;
    yields the relay, the page and the page's problems."""
    async with scripted_fleet(tmp_path) as relay:
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport=viewport)
        problems = watch_errors(page)
        await open_robot_page(page, web.url, [FULL])
        yield relay, page, problems


def sent_keyframe_requests(page: Any, codec: Codec) -> list[str]:
    """``<frame topic> -> <requested topic>`` of each KeyframeRequest the page sends on its
    WebSocket (filled as they are sent; no assertion inside Playwright's callback)."""
    sent: list[str] = []

    def on_frame(payload: str | bytes) -> None:
        if isinstance(payload, bytes) and read_metadata(payload).type == KEYFRAME_REQUEST_TYPE:
            meta, msg = codec.decode(payload)
            sent.append(f"{meta.topic} -> {msg.topic}")

    page.on("websocket", lambda ws: ws.on("framesent", on_frame))
    return sent


@pytest.mark.parametrize("fmt", ["h264", "vp8", "vp9", "av1"])
async def test_video_frames_are_decoded_and_counted(
    fmt: str, tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    units = encode(fmt, 60, width=320, height=240, keyframe_every=15)
    async with video_page(tmp_path, browser, webviz_factory,
                          {"width": 1400, "height": 1100}) as (relay, page, problems):
        VideoFeed(relay.robots["r1"], TOPIC, units, fmt).run()
        await wait_js(page, f"{stat('shown')} >= 10")
        stats = await page.evaluate(STATS)
        assert stats["errors"] == 0 and stats["decoded"] >= 10, stats
        assert stats["decoded"] <= stats["submitted"]
        configured = await page.evaluate(f"fleetviz.views.video.streams.get('{FULL}').configured")
        expected = {"h264": h264_codec_string(units[0].data), "vp8": "vp8",
                    "vp9": "vp09.00.10.08", "av1": "av01.0.04M.08"}[fmt]
        assert configured == expected
        canvas = page.locator("#video-canvas")
        assert await canvas.evaluate("c => [c.width, c.height]") == [320, 240]
        assert await drawn_fraction_within(canvas, PANEL_BG, 0.9) > 0.9
        # The status line says it too (rewritten once a second).
        await wait_js(page, "Number((/(\\d+) decoded, (\\d+) shown/.exec("
                            "document.querySelector('#video-status').textContent) ?? [])[2]) >= 10")
        assert not problems, problems


async def test_a_missing_codec_is_said_on_the_page(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    units = encode("h265", 20, width=320, height=240, keyframe_every=10)
    async with scripted_fleet(tmp_path) as relay:
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page()
        await open_robot_page(page, web.url, [FULL])
        VideoFeed(relay.robots["r1"], TOPIC, units, "h265").run()
        said = page.locator("#video-status", has_text="cannot decode h265")
        await said.wait_for(timeout=TIMEOUT_MS)
        text = await said.text_content() or ""
        assert 'VideoDecoder.isConfigSupported("hev1.1.6.L93.B0") is false' in text
        assert "configure video codec h264, vp8, vp9 or av1" in text
        await wait_js(page, f"{stat('unsupported')} >= 5")
        stats = await page.evaluate(STATS)
        assert stats["decoded"] == 0 and stats["reason"] == "unsupported"
        # An unsupported codec is no reason to pester the robot for keyframes.
        requests = stats["requests"]
        await wait_js(page, f"{stat('received')} >= {stats['received'] + 10}")
        assert await page.evaluate(stat("requests")) == requests


async def test_a_seq_gap_stops_decoding_and_requests_a_keyframe(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    units = encode("h264", 90, width=320, height=240, keyframe_every=30)
    async with scripted_fleet(tmp_path) as relay:
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page()
        requested = sent_keyframe_requests(page, relay.codec)
        await open_robot_page(page, web.url, [FULL])
        feed = VideoFeed(relay.robots["r1"], TOPIC, units, "h264")
        feed.run()
        await wait_js(page, f"{stat('decoded')} >= 5")
        await feed.stop()
        # Go on in order up to a point where the next 7 units are delta frames.
        while any(feed.units[(feed.pos + i) % len(feed.units)].key for i in range(7)):
            await send_one(page, feed)
        # Every unit sent has arrived (link health counts frames before any decoding) and
        # every unit submitted has come out of the decoder.
        await wait_js(page, f"fleetviz.conn.health.topics.get('{FULL}')?.received === {feed.pos}"
                            f" && {stat('decoded')} === {stat('submitted')}")
        # Requests are at most one per 0.5 s across breaks (a page joining mid-stream asked
        # for one a moment ago): wait until the gap below may ask at once.
        gate = f"fleetviz.views.video.streams.get('{FULL}').gate"
        await wait_js(page, f"performance.now() - {gate}.lastRequestMs >= {gate}.requestIntervalMs")
        before = await page.evaluate(STATS)
        assert before["state"] == "decoding" and before["gaps"] == 0, before
        asked = len(requested)
        started = time.monotonic()
        await send_one(page, feed, skip=True)  # one frame lost on the way
        for _ in range(5):
            await send_one(page, feed)
        after = await page.evaluate(STATS)
        # Timed up to the read of the counter, so a request sent while it was read is inside.
        elapsed_s = time.monotonic() - started
        assert after["gaps"] == 1 and after["state"] == "waiting" and after["reason"] == "gap"
        # Nothing decoded from the broken chain, all six skipped, requests 0.5 s apart.
        assert after["submitted"] == before["submitted"]
        assert after["decoded"] == before["decoded"]
        assert after["skipped"] == before["skipped"] + 6
        asked_now = after["requests"] - before["requests"]
        assert 1 <= asked_now <= 1 + int(elapsed_s / 0.5), (asked_now, elapsed_s)
        await wait_js(page, f"fleetviz.keyframeRequests.sent >= {after['requests']}")
        # What went out on the page's WebSocket.
        assert requested[asked:] == [f"/keyframe_requests -> {FULL}"] * asked_now
        # The next keyframe restarts decoding.
        while not feed.peek().key:
            await send_one(page, feed)
        await send_one(page, feed)
        await wait_js(page, f"{stat('decoded')} > {after['decoded']}")
        assert (await page.evaluate(STATS))["state"] == "decoding"


async def test_a_page_that_falls_behind_keeps_its_decoder(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    """Behind, the page skips to the next keyframe on the decoder it has: a new decoder at
    every keyframe paid its start-up again each time, and on a busy page that start-up
    alone kept it behind (9 of 556 frames decoded in 36 s in the 3D scene under load)."""
    units = encode("h264", 60, width=320, height=240, keyframe_every=15)
    async with scripted_fleet(tmp_path) as relay:
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page()
        problems = watch_errors(page)
        await open_robot_page(page, web.url, [FULL])
        feed = VideoFeed(relay.robots["r1"], TOPIC, units, "h264")
        feed.run()
        await wait_js(page, f"{stat('decoded')} >= 3")
        await feed.stop()
        stream = f"fleetviz.views.video.streams.get('{FULL}')"
        # Mark this decoder, then make the page fall behind (what a decode queue past its
        # limit or a full pending list does).
        await page.evaluate(f"(() => {{ const s = {stream}; s.decoder.mark = 'first';"
                            " s.behind(performance.now()); })()")
        behind = await page.evaluate(STATS)
        assert behind["state"] == "waiting" and behind["reason"] == "behind", behind
        assert await page.evaluate(f"{stream}.decoder?.state") == "configured"
        # Delta frames are skipped; the next keyframe goes on the same decoder.
        while not feed.peek().key:
            await send_one(page, feed)
        await send_one(page, feed)
        await wait_js(page, f"{stat('decoded')} > {behind['decoded']}")
        after = await page.evaluate(STATS)
        assert after["state"] == "decoding" and after["errors"] == 0, after
        assert await page.evaluate(f"{stream}.decoder.mark") == "first"
        assert not problems, problems


async def test_a_keyframe_request_reaches_the_publishing_robot(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    """The page's request goes through the relay to the robot that publishes the topic
    (the server's /keyframe_requests routing), and the robot's keyframe is decoded."""
    units = encode("h264", 30, width=320, height=240, keyframe_every=30)
    async with scripted_fleet(tmp_path) as relay:
        r1 = relay.robots["r1"]
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page()
        requested = sent_keyframe_requests(page, relay.codec)
        # Subscribed before the topic ever carried video: the server has no reason to ask
        # for a keyframe itself, so a request the robot gets is the page's.
        await open_robot_page(page, web.url, [FULL])
        feed = VideoFeed(r1, TOPIC, units, "h264", pos=1)  # joins mid-GOP: deltas only
        feed.run()
        frame = await r1.next_frame(KEYFRAME_REQUEST_TYPE, TIMEOUT_MS / 1000)
        await feed.stop()
        meta, msg = relay.codec.decode(frame)
        assert meta.topic == "/keyframe_requests" and msg.topic == FULL
        assert f"/keyframe_requests -> {FULL}" in requested  # the page asked, the relay forwarded
        assert await page.evaluate(stat("decoded")) == 0
        feed.pos = 0  # the robot answers with a keyframe
        await feed.send_next()
        await wait_js(page, f"{stat('decoded')} >= 1")


async def test_a_picture_frozen_while_waiting_for_a_keyframe_looks_stale(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    """Frames keep arriving after a gap but none is decodable until the next keyframe: the
    picture does not move. The panel looked live (its topic was not overdue), and the status
    line's "Waiting for a keyframe" came last, cut off in its three-line box."""
    units = encode("h264", 150, width=320, height=240, keyframe_every=150)  # one GOP: 7.5 s
    async with video_page(tmp_path, browser, webviz_factory,
                          {"width": 1280, "height": 800}) as (relay, page, problems):
        feed = VideoFeed(relay.robots["r1"], TOPIC, units, "h264")
        feed.run(period_s=0.05)
        await wait_js(page, f"{stat('shown')} >= 3")
        await feed.stop()
        await feed.send_next(skip=True)  # one frame lost: every delta frame after it is skipped
        feed.run(period_s=0.05)
        age = page.locator("#panel-video.stale h3 .age", has_text="waiting for a keyframe")
        await age.wait_for(timeout=TIMEOUT_MS)
        assert (await age.text_content() or "").startswith("picture ")
        status = await page.text_content("#video-status") or ""
        assert status.startswith("Waiting for a keyframe (gap;"), status
        assert await page.evaluate(f"fleetviz.conn.health.freshness(['{FULL}']).stale") is False
        # The cycle's keyframe comes round: decoding resumes and the panel is live again.
        await page.locator("#panel-video.stale").wait_for(state="detached", timeout=TIMEOUT_MS)
        assert (await page.evaluate(STATS))["state"] == "decoding"
        await feed.stop()
        assert not problems, problems
