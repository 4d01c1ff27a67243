"""kvloops.write_forever: failures counted, logged once, quietly while JetStream elects."""

from __future__ import annotations

import asyncio
import logging

import pytest
from nats.js.errors import NoStreamResponseError

from fleetctl.server.cluster import kvloops
from tests.support import wait_until


async def run_writes(errors: list[Exception | None], counters: dict[str, int]) -> None:
    """write_forever over *errors* (one per write: raise it, or succeed), until done."""
    results = iter(errors)
    done = asyncio.Event()

    async def tick() -> None:
        await asyncio.sleep(0)

    async def write() -> int:
        error = next(results, None)
        if error is None and not done.is_set() and counters["writes"] >= len(errors) - 1:
            done.set()
        counters["writes"] += 1
        if error is not None:
            raise error
        return 0

    task = asyncio.create_task(kvloops.write_forever(tick, write, counters, "thing", 1.0))
    try:
        await wait_until(done.is_set, 5.0)
    finally:
        task.cancel()


async def test_no_leader_yet_right_after_the_start_is_not_a_warning(
        caplog: pytest.LogCaptureFixture) -> None:
    counters = {"put_failures": 0, "writes": 0}
    with caplog.at_level(logging.INFO, "fleetctl.server.cluster"):
        await run_writes([NoStreamResponseError(), NoStreamResponseError(), None], counters)
    assert counters["put_failures"] == 2
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    messages = [r.getMessage() for r in caplog.records]
    assert any("not written yet" in m for m in messages)
    assert any("writing again" in m for m in messages)


async def test_other_failures_and_late_ones_warn_once(
        caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    counters = {"put_failures": 0, "writes": 0}
    with caplog.at_level(logging.INFO, "fleetctl.server.cluster"):
        await run_writes([TimeoutError(), TimeoutError(), None], counters)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2 and "cannot write the thing" in warnings[0]
    caplog.clear()
    monkeypatch.setattr(kvloops, "ELECTION_WAIT_S", 0.0)  # long after the start
    with caplog.at_level(logging.INFO, "fleetctl.server.cluster"):
        await run_writes([NoStreamResponseError(), None], counters)
    assert [r for r in caplog.records if r.levelno == logging.WARNING]
