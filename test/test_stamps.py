"""StampGuard: a stray stamp is counted and dropped, never taken; a stream that really
moved is followed after a run of consistent stamps."""

from piezo_stage.core.loop.stamps import StampGuard

MS = 1_000_000


def test_a_stray_future_stamp_does_not_poison_the_stream():
    g = StampGuard()
    assert all(g.accept(k * MS) for k in range(1, 100))
    assert not g.accept(10 ** 15 + 100 * MS)      # 10^15 ns ahead: the case
    assert not g.accept(-1_000_000_000)            # sec = -1
    assert all(g.accept(k * MS) for k in range(100, 200))  # the real samples go on
    assert g.dropped == 2 and g.rebased == 0


def test_duplicates_and_old_stamps_are_not_new_and_not_strays():
    g = StampGuard()
    assert g.accept(5 * MS) and not g.accept(5 * MS) and not g.accept(4 * MS)
    assert g.dropped == 0


def test_a_restarted_stream_is_followed_after_a_consistent_run():
    g = StampGuard(rebase_after=50)
    for k in range(1, 1000):
        g.accept(10 ** 12 + k * MS)  # a long-running stream
    took = [g.accept(k * MS) for k in range(1, 80)]  # a driver restarted at 0
    assert took.index(True) == 49 and all(took[49:]) and g.rebased == 1


def test_scattered_strays_never_form_a_run():
    g = StampGuard(rebase_after=5)
    g.accept(MS)
    for k in range(100):
        g.accept(MS * (k + 2))
        assert not g.accept(10 ** 15 * (k % 2 + 1))  # alternating far stamps: no run
    assert g.rebased == 0
