"""The clean stop on SIGTERM / SIGINT (:mod:`depthnerf.train.stop`), with real signals raised in this process
against the rules of the module docstring: the first signal is kept, a second Ctrl+C raises ``KeyboardInterrupt``,
only a single-process validation is abandoned, the previous handlers come back, and the shell's ``128 + n``."""

from __future__ import annotations

import signal
from collections.abc import Iterator

import pytest
import torch

from depthnerf.distributed import DistInfo
from depthnerf.train.stop import StopRequest, ValidationInterrupted, exit_code, signal_name

SINGLE = DistInfo(rank=0, world=1, device=torch.device("cpu"))


@pytest.fixture
def outer() -> Iterator[list[int]]:
    """Handlers of this process before a :class:`StopRequest`: record what reaches them (not one of its own)."""
    seen: list[int] = []
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    for sig in before:
        signal.signal(sig, lambda signum, frame: seen.append(signum))
    try:
        yield seen
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def test_exit_status_is_the_shells_128_plus_the_signal_number():
    """Ground truth: the shell's status of a process ended by signal n, 128 + n (SIGINT 2, SIGTERM 15)."""
    assert exit_code(signal.SIGINT) == 130 and exit_code(signal.SIGTERM) == 143
    assert (signal_name(signal.SIGTERM), signal_name(signal.SIGINT)) == ("SIGTERM", "SIGINT")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_is_recorded_and_the_previous_handlers_come_back(outer, sig):
    """Inside the block a signal only sets the request; after it, the handlers installed before are back (a signal
    reaches them again)."""
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    with StopRequest(SINGLE) as stop:
        assert not stop.requested()
        signal.raise_signal(sig)
        assert stop.requested() and stop.signum == sig and outer == []
    assert {s: signal.getsignal(s) for s in handlers} == handlers
    signal.raise_signal(sig)
    assert outer == [sig]


@pytest.mark.parametrize("first, second", [(signal.SIGTERM, signal.SIGTERM), (signal.SIGINT, signal.SIGTERM)])
def test_the_first_signal_is_kept_and_a_second_sigterm_does_not_interrupt(outer, first, second):
    with StopRequest(SINGLE) as stop:
        signal.raise_signal(first)
        try:
            signal.raise_signal(second)
        except KeyboardInterrupt:
            pytest.fail("a SIGTERM after a first signal raised KeyboardInterrupt")
        assert stop.signum == first


@pytest.mark.parametrize("first", [signal.SIGTERM, signal.SIGINT])
def test_a_second_ctrl_c_raises_keyboard_interrupt(outer, first):
    with StopRequest(SINGLE) as stop:
        signal.raise_signal(first)
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
        assert stop.signum == first


def test_a_signal_abandons_a_single_process_validation_but_nothing_after_it(outer):
    with StopRequest(SINGLE) as stop:
        with stop.interruptible():
            pass
        signal.raise_signal(signal.SIGTERM)  # after the block: only recorded
        assert stop.signum == signal.SIGTERM
    with StopRequest(SINGLE) as stop:
        with pytest.raises(ValidationInterrupted), stop.interruptible():
            signal.raise_signal(signal.SIGTERM)
        assert stop.signum == signal.SIGTERM
        with pytest.raises(ValidationInterrupted), stop.interruptible():  # a signal already came: at once
            pytest.fail("the block ran although a stop signal had come")


def test_with_several_ranks_a_validation_is_not_abandoned(outer):
    """Several ranks: rank 0 finishes the validation (the others wait for it in the next step's reduction)."""
    with StopRequest(DistInfo(rank=0, world=2, device=torch.device("cpu"))) as stop:
        with stop.interruptible():
            signal.raise_signal(signal.SIGTERM)
            finished = True
        assert finished and stop.signum == signal.SIGTERM
