"""What the ROS middleware (RMW) in use gives DC: here, publication sequence numbers.

destination_server deduplicates the replayed records of publishers without DC's hand-off key, and
counts records lost on the way from them, by the DDS publication sequence number rclpy hands over in
MessageInfo (dc_destinations.hop). Fast DDS fills it; Cyclone DDS leaves it 0
(rmw's RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED). The RMW says which through
``rmw_feature_supported`` (rmw/features.h), which rclpy does not expose: it is asked through ctypes.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable

# rmw_feature_t RMW_FEATURE_MESSAGE_INFO_PUBLICATION_SEQUENCE_NUMBER (rmw/features.h, Humble and later).
FEATURE_PUBLICATION_SEQUENCE_NUMBER = 0
# What is known when the RMW's library cannot be asked (an RMW built without the symbol, a renamed library).
KNOWN = {"rmw_fastrtps_cpp": True, "rmw_fastrtps_dynamic_cpp": True, "rmw_cyclonedds_cpp": False}


def ask_rmw(identifier: str, feature: int) -> bool | None:
    """The RMW library's own ``rmw_feature_supported(feature)``; None when it cannot be asked.

    rclpy has loaded ``lib<identifier>.so`` already: dlopen by that name finds the loaded one.
    """
    try:
        library = ctypes.CDLL(f"lib{identifier}.so")
        supported = library.rmw_feature_supported
    except (OSError, AttributeError):
        return None
    supported.restype = ctypes.c_bool
    supported.argtypes = [ctypes.c_int]
    return bool(supported(feature))


def publication_sequence_numbers(identifier: str, ask: Callable[[str, int], bool | None] = ask_rmw) -> bool | None:
    """Whether RMW ``identifier`` fills MessageInfo's publication_sequence_number; None if unknown."""
    answer = ask(identifier, FEATURE_PUBLICATION_SEQUENCE_NUMBER)
    return KNOWN.get(identifier) if answer is None else answer


def no_sequence_numbers_line(identifier: str, external_topics: list[str]) -> str:
    """destination_server's startup line for an RMW without publication sequence numbers."""
    whose = (
        f"your own nodes' records on {', '.join(external_topics)}"
        if external_topics
        else "records of publishers without DC's hand-off key (none among this configuration's inputs)"
    )
    return (
        f"the middleware {identifier} gives no publication sequence numbers: {whose}, and DC's servers' if "
        "their hand-off is off (unacked_limit_records: 0), are not deduplicated, so after a restart of "
        "destination_server what their publishers' history still holds is delivered again (duplicates, "
        "never a loss), and records lost between them and DC are not counted. DC's hand-off keys the "
        "records of its own servers on any middleware (docs/delivery.md)"
    )
