"""Sequence-number gaps: the messages a subscription never got."""

from __future__ import annotations

from aefabmap_ros.nodes.delivery import SEQUENCE_NUMBER_UNSUPPORTED, SequenceGaps


def test_gaps_between_received_messages_are_counted() -> None:
    gaps = SequenceGaps()
    assert gaps.observe(1, publishers=1) == 0  # the first message: nothing to compare with
    assert gaps.observe(2, publishers=1) == 0
    assert gaps.observe(7, publishers=1) == 4  # 3, 4, 5, 6 never arrived
    assert gaps.observe(8, publishers=1) == 0
    assert gaps.missed == 4


def test_a_first_message_late_in_the_sequence_is_not_a_loss() -> None:
    gaps = SequenceGaps()  # messages 1-41 went out before this subscription matched: not meant for it
    assert gaps.observe(42, publishers=1) == 0
    assert gaps.missed == 0


def test_a_restarted_publisher_numbers_from_one_again() -> None:
    gaps = SequenceGaps()
    gaps.observe(100, publishers=1)
    assert gaps.observe(1, publishers=1) == 0
    assert gaps.observe(3, publishers=1) == 1
    assert gaps.missed == 1


def test_nothing_is_judged_with_several_publishers_or_without_numbers() -> None:
    gaps = SequenceGaps()
    gaps.observe(1, publishers=1)
    assert gaps.observe(50, publishers=2) == 0  # whose number is it? rclpy does not say
    assert gaps.observe(60, publishers=1) == 0  # a fresh start after the unjudged stretch
    assert gaps.observe(SEQUENCE_NUMBER_UNSUPPORTED, publishers=1) == 0
    assert gaps.missed == 0 and gaps.unjudged == 2
