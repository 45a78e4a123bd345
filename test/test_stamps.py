"""StampGuard: a stray stamp is counted and dropped, never taken; a stream that really
moved is followed after a run of consistent stamps."""

from piezo_stage.core.loop.stamps import Publications, StampGuard, publication_key

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


def test_a_publication_is_taken_once_and_the_same_content_published_again_is_new():
    """The identity is the publication (source timestamp, sequence number): a second
    delivery of one (volatile and latched) is not new; another publication is, whatever
    its bytes; a delivery without an identity is always new; only the newest are
    remembered."""
    p = Publications(remember=3)
    a = publication_key({"source_timestamp": 10, "publication_sequence_number": 1})
    assert p.first(a) and not p.first(a) and p.repeated == 1
    again = publication_key({"source_timestamp": 11, "publication_sequence_number": 2})
    assert p.first(again)  # the same trajectory sent again: a new request
    other_writer = publication_key({"source_timestamp": 12,
                                    "publication_sequence_number": 1})
    assert p.first(other_writer)
    assert publication_key({"source_timestamp": None}) is None
    assert publication_key(None) is None
    assert p.first(None) and p.first(None)
    for k in range(20, 23):
        p.first((k, k))
    assert p.first(a)  # forgotten: three newer ones since


def test_a_request_is_taken_once_however_often_it_is_sent():
    """A frame_id that begins ``request:`` names one request: admitted once, whatever
    its publications; any other frame_id names nothing (every publication is new); a
    publication delivered twice is admitted once either way."""
    from piezo_stage.core.loop.stamps import request_key
    p = Publications()
    key = iter(range(100))
    pub = lambda: (next(key), 0)  # noqa: E731 - a new publication each call
    r = request_key("request:/stage/trajectory@1a#1")
    assert r is not None
    assert p.admit(pub(), r) and not p.admit(pub(), r) and not p.admit(pub(), r)
    assert p.repeated == 2
    assert p.admit(pub(), request_key("request:/stage/trajectory@1a#2"))
    assert p.admit(pub(), request_key("request:/stage/trajectory@1b#1"))  # restarted
    once = pub()
    assert p.admit(once, request_key("request:x")) and not p.admit(once, None)
    for plain in ("", "scan line 3", "request", "request:", "Request:x"):
        assert request_key(plain) is None
        assert p.admit(pub(), request_key(plain)) and p.admit(pub(), request_key(plain))


def test_the_sample_guard_drops_and_counts_in_the_cores_counters():
    """One guard for every loop core: a malformed message, a duplicate, a stray stamp
    and (real time) a sample already past are dropped, each counted in the counters it
    was given (the core's); a sample on time passes, and an answer the core judged late
    or past its tick is dropped and counted."""
    from piezo_stage.core.loop.stamps import SampleGuard
    stats = {"bad_messages": 0, "stray_stamps": 0, "late_dropped": 0}
    g = SampleGuard(stats)
    g.malformed()
    assert stats["bad_messages"] == 1
    assert g.admit(1_000) and not g.admit(1_000)  # a duplicate changes nothing
    assert stats == {"bad_messages": 1, "stray_stamps": 0, "late_dropped": 0}
    assert not g.admit(10 ** 18)  # a stray stamp far ahead: dropped, counted
    assert stats["stray_stamps"] == 1
    assert g.admit(2_000, now_ns=1_500)  # real time, on time
    assert not g.admit(3_000, now_ns=5_000) and stats["late_dropped"] == 1  # past
    assert g.on_time(9_000, None) and g.on_time(9_000, 8_000)
    assert not g.on_time(9_000, None, late=True) and not g.on_time(9_000, 9_500)
    assert stats["late_dropped"] == 3
