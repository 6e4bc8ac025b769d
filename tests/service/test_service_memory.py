"""Giving freed memory back to the system (`service.uploads.memory.FreedMemory`), with a stand-in
for glibc that counts its calls; the real effect on a server's resident memory is measured in
test_service_server.py and test_service_limits.py."""

from __future__ import annotations

import asyncio

import pytest

from crestereo_pp.service.uploads import memory

DELAY_S = 0.05


class CountingLibc:
    """glibc's two calls that `memory` makes, counted."""

    def __init__(self) -> None:
        self.trims = 0

    def mallopt(self, parameter: int, value: int) -> int:
        return 1

    def malloc_trim(self, pad: int) -> int:
        self.trims += 1
        return 1


@pytest.fixture
def libc(monkeypatch: pytest.MonkeyPatch) -> CountingLibc:
    counting = CountingLibc()
    monkeypatch.setattr(memory, "_libc", lambda: counting)
    return counting


def test_many_ends_within_the_delay_trim_once_after_it(libc):
    async def scenario() -> list[int]:
        freed = memory.FreedMemory()
        for _ in range(5):
            freed.soon(DELAY_S)
        seen = [libc.trims]
        await asyncio.sleep(4 * DELAY_S)
        seen.append(libc.trims)
        freed.soon(DELAY_S)
        await asyncio.sleep(4 * DELAY_S)
        return [*seen, libc.trims]

    assert asyncio.run(scenario()) == [0, 1, 2]


def test_a_trim_is_skipped_when_work_began_before_it_and_made_when_the_work_ends(libc):
    async def scenario() -> list[int]:
        freed = memory.FreedMemory()
        busy = False
        freed.soon(DELAY_S, unless=lambda: busy)
        busy = True  # a request arrives before the trim
        await asyncio.sleep(4 * DELAY_S)
        skipped = libc.trims
        busy = False  # and ends
        freed.soon(DELAY_S, unless=lambda: busy)
        await asyncio.sleep(4 * DELAY_S)
        return [skipped, libc.trims]

    assert asyncio.run(scenario()) == [0, 1]


def test_one_veto_holds_off_a_trim_that_another_caller_asked_for_without_one(libc):
    async def scenario() -> int:
        freed = memory.FreedMemory()
        freed.soon(DELAY_S)  # a stream ended
        freed.soon(DELAY_S, unless=lambda: True)  # a request ended, and another is in progress
        await asyncio.sleep(4 * DELAY_S)
        return libc.trims

    assert asyncio.run(scenario()) == 0


def test_a_sooner_trim_is_not_held_back_by_a_later_one_already_due(libc):
    async def scenario() -> list[int]:
        freed = memory.FreedMemory()
        freed.soon(100 * DELAY_S)  # the server went idle: a trim a long while later
        freed.soon(DELAY_S)  # a stream ended: sooner
        await asyncio.sleep(4 * DELAY_S)
        seen = libc.trims
        freed.soon(100 * DELAY_S)
        freed.soon(200 * DELAY_S)  # a later one changes nothing
        await asyncio.sleep(4 * DELAY_S)
        return [seen, libc.trims]

    assert asyncio.run(scenario()) == [1, 1]
