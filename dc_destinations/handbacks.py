"""How often each message of a JetStream consumer was handed back by ``dc ingest`` workers, shared by
every worker on that consumer: a JetStream key-value bucket keyed by the message's stream sequence.

A hand-back (a nak after ``handback_delay``, because the worker's buffer dropped the record) is no
failure of the record, so it must not count against ``retry_limit``; but it raises the message's
``num_delivered`` as a worker killed on it does, and JetStream tells the next worker nothing else.
Each worker writes the count before its nak and reads it only for a message delivered before
(``num_delivered`` > 1): a message delivered once, the normal path, costs nothing here. Why a bucket
and not a re-published copy of the message: docs/fleet.md, "Bounded redelivery".
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import Sequence
from typing import Any

from dc_core.errors import DcError

# How long an entry lasts after the message's last hand-back when the stream keeps messages for ever
# (no max_age): a message not delivered again within it has its hand-backs counted again.
DEFAULT_TTL = 7 * 24 * 3600.0


def bucket_name(stream: str, consumer: str) -> str:
    """The bucket of ``consumer`` on ``stream`` (one per consumer: each counts its own deliveries)."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", f"dc_handbacks_{stream}_{consumer}")


def _stored_at(msg: Any) -> str:
    # The message's time in the stream, the same at every delivery: an entry left by a stream that was
    # deleted and made again (its sequences start over) does not match the new stream's message.
    return str(msg.metadata.timestamp.isoformat())


class HandbackRecord:
    """The shared hand-back counts of one consumer's messages (:meth:`open` makes the bucket once)."""

    def __init__(self, kv: Any, name: str) -> None:
        self._kv = kv
        self.name = name

    @classmethod
    async def open(cls, js: Any, stream: str, consumer: str) -> HandbackRecord:
        """The bucket of ``consumer``, made if missing: replicated as ``stream`` is, its entries
        kept as long as the stream keeps its messages (``DEFAULT_TTL`` without a max_age)."""
        import nats.js.errors
        from nats.js.api import KeyValueConfig, StorageType

        name = bucket_name(stream, consumer)
        try:
            try:
                return cls(await js.key_value(name), name)
            except nats.js.errors.BucketNotFoundError:
                pass
            config = (await js.stream_info(stream)).config
            kv = await js.create_key_value(
                KeyValueConfig(
                    bucket=name,
                    description=f"dc ingest: hand-backs of consumer {consumer} of stream {stream}",
                    history=1,
                    ttl=config.max_age or DEFAULT_TTL,
                    replicas=config.num_replicas or 1,
                    storage=StorageType.FILE,
                )
            )
        except Exception as exc:
            raise DcError(
                f"cannot open or make the key-value bucket {name} (the hand-backs of consumer {consumer}; "
                f"the worker's NATS user needs JetStream access to $KV.{name}.> and stream KV_{name}): {exc!r}"
            ) from exc
        return cls(kv, name)

    async def counts(self, messages: Sequence[Any]) -> dict[int, int | None]:
        """For each message delivered before, by its stream sequence: how often workers handed it
        back; None when the bucket could not be read. Messages delivered once are not looked up."""
        again = [msg for msg in messages if msg.metadata.num_delivered > 1]
        if not again:
            return {}
        counts = await asyncio.gather(*(self._count(msg) for msg in again))
        return {msg.metadata.sequence.stream: n for msg, n in zip(again, counts, strict=True)}

    async def _count(self, msg: Any) -> int | None:
        import nats.js.errors

        try:
            entry = await self._kv.get(str(msg.metadata.sequence.stream))
        except nats.js.errors.KeyNotFoundError:  # never handed back (or forgotten after the TTL)
            return 0
        except Exception:
            return None
        count, _, stored_at = (entry.value or b"").decode("utf-8", "replace").partition(" ")
        return int(count) if count.isdigit() and stored_at == _stored_at(msg) else 0

    async def record(self, msg: Any, handbacks: int) -> None:
        """The message was handed back ``handbacks`` times, this hand-back included. Raises when the
        bucket cannot be written."""
        await self._kv.put(str(msg.metadata.sequence.stream), f"{handbacks} {_stored_at(msg)}".encode())
