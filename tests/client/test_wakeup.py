"""Wakeup: set before, during and never; one waiter."""

from __future__ import annotations

import asyncio

import pytest

from fleetctl.client.wakeup import Wakeup


def test_already_set_returns_at_once() -> None:
    async def main() -> bool:
        w = Wakeup()
        w.set()
        return await w.wait(60.0)

    assert asyncio.run(main()) is True


def test_set_from_a_callback_wakes_the_waiter() -> None:
    async def main() -> tuple[bool, float]:
        loop = asyncio.get_running_loop()
        w = Wakeup()
        loop.call_soon(w.set)
        start = loop.time()
        return await w.wait(60.0), loop.time() - start

    woke, waited = asyncio.run(main())
    assert woke and waited < 30.0  # woken by set(), not by the 60 s timeout


def test_timeout_returns_false_and_clear_resets() -> None:
    async def main() -> tuple[bool, bool, bool]:
        w = Wakeup()
        timed_out = await w.wait(0.01)
        w.set()
        w.clear()
        return timed_out, w.is_set(), await w.wait(0.01)

    assert asyncio.run(main()) == (False, False, False)


def test_second_waiter_is_refused() -> None:
    async def main() -> None:
        w = Wakeup()
        first = asyncio.ensure_future(w.wait(60.0))
        await asyncio.sleep(0)  # let the first waiter register
        try:
            with pytest.raises(RuntimeError, match="one waiter"):
                await w.wait(60.0)
        finally:
            w.set()
            await first

    asyncio.run(main())
