"""The loan's per-message path in C (``buffer_pubsub._loans``): a pooled slot's tokens and
re-arm, the pool's choice of a slot, the Loan context manager, and typed errors on misuse.

The rules are those of :mod:`buffer_pubsub.loan`'s docstring; ``tests/test_loans.py`` checks
them through publishers, these check the C types one call at a time.
"""

from __future__ import annotations

import gc

import pytest

from buffer_pubsub.errors import LoanError
from buffer_pubsub.loan import Loan, _Slot
from buffer_pubsub.loan import _loans as native
from rosidl_buffer import Buffer, BufferImplBase
from rosidl_buffer.messages import get_message_type

TENSOR = "tensor_msgs/msg/ExperimentalTensor"


class _Rearm(BufferImplBase):
    """A storage whose re-arm answer the test sets (and counts)."""

    def __init__(self, answer: bool = True) -> None:
        self.answer = answer
        self.calls = 0

    def get_backend_type(self) -> str:
        return "test"

    def size(self) -> int:
        return 4

    def reclaim(self) -> bool:
        self.calls += 1
        return self.answer

    def clone(self) -> _Rearm:
        return _Rearm(self.answer)

    def to_cpu(self) -> BufferImplBase:
        raise NotImplementedError


def _slot(answer: bool = True):
    msg = get_message_type(TENSOR)(data=Buffer(_Rearm(answer)))
    return msg, _Slot(msg, [(msg, "data")])


def test_a_new_slot_is_on_loan_and_keeps_its_storage():
    msg, slot = _slot()
    assert slot.loaned is True and slot.msg is msg
    assert slot.impls == (msg.data.get_impl(),)


def test_reusable_hands_out_a_fresh_buffer_and_the_last_one_is_a_token():
    msg, slot = _slot()
    handed = msg.data  # what the last loan handed out: its holder's token
    assert slot.reusable() is False  # the token is alive
    fresh = msg.data
    assert fresh is not handed and fresh.get_impl() is handed.get_impl()
    del handed, fresh
    gc.collect()
    assert slot.reusable() is True
    assert slot.impls[0].calls == 1  # re-armed only once no token was alive


def test_a_buffer_the_user_put_in_place_is_not_a_token():
    msg, slot = _slot()
    impl = msg.data.get_impl()
    mine = Buffer(_Rearm())
    msg.data = mine  # the user's own: kept by the user, never blocks the pool
    assert slot.reusable() is True
    assert msg.data is not mine and msg.data.get_impl() is impl  # the pool's storage again


def test_a_storage_that_is_still_read_is_not_reusable():
    msg, slot = _slot(answer=False)
    del msg
    assert slot.reusable() is False


def test_reuse_takes_the_least_recently_loaned_reusable_slot_and_moves_it_last():
    (_, first), (held_msg, held), (_, second), (_, busy) = _slot(), _slot(), _slot(), _slot()
    for slot in (first, held, second):
        slot.loaned = False  # (busy stays on loan)
    kept = held_msg.data  # the Buffer held's last loan handed out: a token
    slots = [first, held, busy, second]
    assert native.reuse(slots) is first
    assert first.loaned is True and slots == [held, busy, second, first]
    assert native.reuse(slots) is second
    assert slots == [held, busy, first, second]
    assert native.reuse(slots) is None  # held is held, the others are on loan
    del kept
    gc.collect()
    assert native.reuse(slots) is held and slots[-1] is held


def test_reuse_and_slots_refuse_what_they_do_not_know():
    with pytest.raises(TypeError):
        native.reuse((1, 2))
    with pytest.raises(TypeError):
        native.reuse([object()])
    with pytest.raises(TypeError):
        _Slot(object(), [("not", "a place", "tuple")])
    with pytest.raises(ValueError):
        _Slot.__new__(_Slot).reusable()
    with pytest.raises(TypeError):
        _Slot(object(), [(object(), 3)])


class _Pool:
    def __init__(self, msg, slot) -> None:
        self.msg, self.slot = msg, slot
        self.in_blocks: set[int] = set()

    def take(self, factory, max_loans):
        return self.msg, self.slot


def _loan(publish):
    msg, slot = _slot()
    pool = _Pool(msg, slot)
    return pool, slot, Loan(pool, publish, lambda: msg)


def test_a_loan_publishes_on_exit_and_gives_its_slot_back():
    sent = []
    pool, slot, loan = _loan(sent.append)
    with loan as msg:
        assert pool.in_blocks == {id(msg)} and slot.loaned
    assert sent == [msg] and not pool.in_blocks and slot.loaned is False


def test_an_exception_in_the_block_publishes_nothing():
    sent = []
    pool, slot, loan = _loan(sent.append)
    with pytest.raises(KeyError):
        with loan:
            raise KeyError("in the block")
    assert sent == [] and not pool.in_blocks and slot.loaned is False


def test_a_publish_that_raises_still_gives_the_slot_back():
    def publish(msg):
        raise RuntimeError("the transport failed")

    pool, slot, loan = _loan(publish)
    with pytest.raises(RuntimeError, match="the transport failed"):
        with loan:
            pass
    assert not pool.in_blocks and slot.loaned is False


def test_a_loan_is_entered_once_and_checks_its_arguments():
    _, _, loan = _loan(lambda msg: None)
    with loan:
        with pytest.raises(LoanError, match="entered once"):
            loan.__enter__()
    with pytest.raises(TypeError):
        Loan(object(), "not callable", lambda: None)
    with pytest.raises(ValueError):
        Loan.__new__(Loan).__enter__()

    class _Odd(_Pool):
        def take(self, factory, max_loans):
            return self.msg, "not a slot"

    msg, slot = _slot()
    with pytest.raises(TypeError, match="_Slot or None"):
        Loan(_Odd(msg, slot), lambda m: None, lambda: msg).__enter__()


# ------------------------------------------------------------------ re-entrancy (user code runs)
class _Owner:
    """A message-like owner whose buffer field runs ``hook`` once when read (user code)."""

    def __init__(self) -> None:
        self._data = Buffer(_Rearm())
        self.hook = None

    @property
    def data(self):
        hook, self.hook = self.hook, None
        if hook is not None:
            hook()
            [bytearray(80) for _ in range(2000)]  # reuse freed memory, as a crash would need
        return self._data

    @data.setter
    def data(self, value) -> None:
        self._data = value


def test_a_slot_keeps_its_places_whatever_its_caller_does_with_the_list():
    owner = _Owner()
    places = [(owner, "data")]
    slot = _Slot(owner, places)
    places.append((_Owner(), "data"))  # the caller's list: not the slot's any more
    places.clear()
    impl = owner._data.get_impl()
    assert slot.reusable() is True  # its one place, refreshed; nothing else read
    assert owner._data.get_impl() is impl and slot.impls == (impl,)


def test_a_slot_re_initialized_by_user_code_during_reusable_does_not_crash():
    owner, other = _Owner(), _Owner()
    slot = _Slot(owner, [(owner, "data")])
    owner.hook = lambda: slot.__init__(other, [(other, "data")])
    assert slot.reusable() in (True, False)  # the old state is kept alive until the call ends
    assert slot.msg is other


def test_enter_returns_a_live_message_even_if_user_code_ends_the_loan_inside_it():
    freed = []

    class _Msg:
        def __del__(self) -> None:
            freed.append(id(self))

    class _Reentrant:
        ended = False

        def take(self, factory, max_loans):
            return _Msg(), None  # the tuple holds the only reference

        @property
        def in_blocks(self) -> set:
            if not self.ended:
                self.ended = True
                loan.__exit__(ValueError, None, None)  # the loan ends inside __enter__
            return set()

    loan = Loan(_Reentrant(), lambda msg: None, lambda: None)
    msg = loan.__enter__()
    assert type(msg) is _Msg and id(msg) not in freed
    del msg
    assert len(freed) == 1
