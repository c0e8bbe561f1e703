from aefabmap_ros.visualization.candidates import Candidate, CandidateWatch


def _candidate(query_ns: int) -> Candidate:
    return Candidate(query_ns, query_ns - 1000, 1, 0, 0.99)


def test_a_candidate_without_a_closure_is_refused_after_the_timeout_only():
    watch = CandidateWatch(timeout_s=2.0)
    watch.add(_candidate(10), now_s=0.0)
    watch.add(_candidate(20), now_s=1.0)
    assert watch.refused(1.9) == []
    assert [c.query_ns for c in watch.refused(2.0)] == [10]
    assert [c.query_ns for c in watch.refused(3.5)] == [20]
    assert watch.refused(100.0) == [] and len(watch) == 0


def test_a_verified_query_is_never_refused_whichever_arrives_first():
    watch = CandidateWatch(timeout_s=1.0)
    watch.add(_candidate(10), now_s=0.0)
    watch.verified(10)  # the closure after its candidate
    watch.verified(20)  # the closure before its candidate (another process, another queue)
    watch.add(_candidate(20), now_s=0.0)
    assert watch.refused(10.0) == []


def test_pending_candidates_are_bounded():
    watch = CandidateWatch(timeout_s=1.0, max_pending=3)
    for stamp in range(5):
        watch.add(_candidate(stamp), now_s=0.0)
    assert [c.query_ns for c in watch.refused(5.0)] == [2, 3, 4]


def test_a_candidate_passed_over_by_a_later_querys_closure_is_refused_at_once():
    watch = CandidateWatch(timeout_s=60.0)
    for stamp in (10, 20, 30):
        watch.add(_candidate(stamp), now_s=0.0)
    watch.verified(20)
    assert [c.query_ns for c in watch.refused(0.0)] == [10]  # 30 may still be verified
    assert watch.refused(1.0) == [] and len(watch) == 1
