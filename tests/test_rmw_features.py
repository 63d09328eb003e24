"""dc_core.rmw_features: whether the middleware gives publication sequence numbers, asked of the RMW itself."""

from __future__ import annotations

import rclpy
from rclpy.context import Context
from rclpy.utilities import get_rmw_implementation_identifier

from dc_core.rmw_features import (
    FEATURE_PUBLICATION_SEQUENCE_NUMBER,
    ask_rmw,
    no_sequence_numbers_line,
    publication_sequence_numbers,
)
from tests.domains import fresh_domain_id


def test_fast_dds_says_it_gives_them() -> None:
    context = Context()
    rclpy.init(context=context, domain_id=fresh_domain_id())  # loads the RMW's library
    try:
        identifier = get_rmw_implementation_identifier()
        assert identifier == "rmw_fastrtps_cpp"
        assert ask_rmw(identifier, FEATURE_PUBLICATION_SEQUENCE_NUMBER) is True
        assert publication_sequence_numbers(identifier) is True
    finally:
        rclpy.shutdown(context=context)


def test_what_is_known_when_the_rmw_cannot_be_asked() -> None:
    cannot_ask = lambda identifier, feature: None  # noqa: E731
    assert ask_rmw("rmw_no_such_middleware", FEATURE_PUBLICATION_SEQUENCE_NUMBER) is None
    assert publication_sequence_numbers("rmw_cyclonedds_cpp", cannot_ask) is False
    assert publication_sequence_numbers("rmw_fastrtps_cpp", cannot_ask) is True
    assert publication_sequence_numbers("rmw_zenoh_cpp", cannot_ask) is None
    # The RMW's own answer wins over what is known by name.
    assert publication_sequence_numbers("rmw_cyclonedds_cpp", lambda identifier, feature: True) is True


def test_the_line_without_inputs_of_your_own_nodes() -> None:
    line = no_sequence_numbers_line("rmw_cyclonedds_cpp", [])
    assert "none among this configuration's inputs" in line
    assert "unacked_limit_records: 0" in line and "duplicates, never a loss" in line
